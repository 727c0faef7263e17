"""SOUP as an SB3 algorithm: presets, strategies, VecEnvs, Dict observations, callbacks, save/load, seeding, errors."""

import re

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_soup import PRESETS, SOUP, BootstrappedDictReplayBuffer, DecayingNormalActionNoise

SMALL = dict(learning_starts=50, batch_size=32, buffer_size=2000)


class DictPendulum(gym.ObservationWrapper):
    """Pendulum with a Dict observation (angle part and velocity part)."""

    def __init__(self):
        super().__init__(gym.make("Pendulum-v1"))
        self.observation_space = spaces.Dict(
            {"angle": spaces.Box(-1, 1, (2,), np.float32), "velocity": spaces.Box(-8, 8, (1,), np.float32)}
        )

    def observation(self, obs):
        return {"angle": obs[:2], "velocity": obs[2:]}


@pytest.mark.parametrize("preset", sorted(PRESETS))
@pytest.mark.parametrize("train_heads", ["active", "all"])
def test_every_preset_learns_a_few_hundred_steps(preset, train_heads):
    model = SOUP("MlpPolicy", "Pendulum-v1", preset=preset, n_heads=3, train_heads=train_heads, seed=0, **SMALL)
    assert model.preset == preset
    model.learn(250)
    assert model.num_timesteps == 250
    expected_heads = {k: (3 if v == "K" else v) for k, v in PRESETS[preset].items() if k.startswith("n_")}
    assert model.policy.n_actor_heads == expected_heads["n_actor_heads"]
    assert model.policy.n_critic_heads == expected_heads["n_critic_heads"]
    assert np.isfinite(model.logger.name_to_value["train/critic_loss"])


@pytest.mark.parametrize("confidence", ["none", "fixed", "decayed", "adaptive"])
def test_every_confidence_strategy_learns_a_few_hundred_steps(confidence):
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, confidence=confidence, seed=0, verbose=0, **SMALL)
    model.learn(250, log_interval=1)
    logged = model.logger.name_to_value
    # log_interval=1 dumps at each episode end; the last dump (step 200) reset the stats, so re-check what it wrote
    assert model.policy.confidence.__class__.__name__.lower().startswith(confidence if confidence != "none" else "no")
    assert "train/noise_std" in logged


def test_ensemble_statistics_are_logged(tmp_path):
    from stable_baselines3.common.logger import configure

    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, seed=0, **SMALL)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(400, log_interval=1)
    import pandas as pd

    log = pd.read_csv(tmp_path / "progress.csv")
    for column in [
        "selection/head_0",
        "selection/head_2",
        "confidence/head_0",
        "confidence/head_2",
        "rollout/q_spread",
        "train/critic_loss",
        "train/actor_loss",
        "train/confidence_loss",
        "train/noise_std",
    ]:
        assert column in log.columns, column
    last = log.iloc[-1]
    assert last[["selection/head_0", "selection/head_1", "selection/head_2"]].sum() == pytest.approx(1.0)
    assert 0 < last["confidence/head_1"] <= 1


def test_n_envs_2_and_set_env():
    env = make_vec_env("Pendulum-v1", n_envs=2, seed=0)
    model = SOUP("MlpPolicy", env, n_heads=3, seed=0, **SMALL)
    model.learn(200)
    assert model.num_timesteps == 200 and model._active_pairs.shape == (2,)
    assert model.replay_buffer.masks.shape[1:] == (2, 3)
    model.set_env(make_vec_env("Pendulum-v1", n_envs=2, seed=1))
    model.learn(100, reset_num_timesteps=False)
    assert model.num_timesteps == 300


def test_dict_observations(tmp_path):
    model = SOUP("MultiInputPolicy", DictPendulum(), n_heads=3, seed=0, **SMALL)
    assert isinstance(model.replay_buffer, BootstrappedDictReplayBuffer)
    model.learn(150)
    obs = model.env.reset()
    action, _ = model.predict(obs, deterministic=True)
    model.save(tmp_path / "dict")
    loaded = SOUP.load(tmp_path / "dict")
    assert np.allclose(loaded.predict(obs, deterministic=True)[0], action)


@pytest.mark.parametrize("confidence", ["adaptive", "decayed"])
def test_save_load_gives_identical_actions_and_state(tmp_path, confidence):
    # a decaying noise, so that its schedule is part of the state that must survive
    noise = DecayingNormalActionNoise(np.zeros(1), np.full(1, 0.1), decay=0.999)
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=4, confidence=confidence, action_noise=noise, seed=0, **SMALL)
    model.learn(300)
    model.save(tmp_path / "soup")
    loaded = SOUP.load(tmp_path / "soup", env=make_vec_env("Pendulum-v1"))
    obs = np.random.default_rng(0).normal(size=(20, 3)).astype(np.float32)
    assert np.array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    for key, value in model.policy.state_dict().items():
        assert th.equal(value, loaded.policy.state_dict()[key]), key
    for name in ("actor", "critic"):
        saved = getattr(model, name).optimizer.state_dict()["state"]
        restored = getattr(loaded, name).optimizer.state_dict()["state"]
        assert all(th.equal(saved[i]["n_steps"], restored[i]["n_steps"]) for i in saved)
    if confidence == "adaptive":
        assert loaded.policy.confidence.optimizer.state_dict()["state"]
        assert float(loaded.policy.confidence.reward_baseline) == float(model.policy.confidence.reward_baseline)
    else:
        assert float(loaded.policy.confidence.n_steps) == 300  # one decay per env-step
    assert loaded.action_noise.n_calls == model.action_noise.n_calls == 300 - SMALL["learning_starts"]
    assert loaded.action_noise.sigma == model.action_noise.sigma < 0.1  # the schedule goes on where it was
    assert (loaded.n_heads, loaded.confidence, loaded.mask_prob) == (4, confidence, model.mask_prob)
    loaded.learn(100, reset_num_timesteps=False)
    assert loaded.num_timesteps == 400


def test_same_seed_same_run():
    params = []
    for _ in range(2):
        model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, seed=42, **SMALL)
        model.learn(200)
        params.append(th.nn.utils.parameters_to_vector(model.policy.parameters()))
    assert th.equal(params[0], params[1])
    other = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, seed=43, **SMALL).learn(200)
    assert not th.equal(params[0], th.nn.utils.parameters_to_vector(other.policy.parameters()))


def test_callbacks_progress_bar_and_tensorboard(tmp_path):
    eval_env = make_vec_env("Pendulum-v1", n_envs=1, seed=5)
    eval_callback = EvalCallback(eval_env, n_eval_episodes=1, eval_freq=100, log_path=str(tmp_path / "eval"))
    checkpoint = CheckpointCallback(save_freq=100, save_path=str(tmp_path / "ckpt"), save_replay_buffer=True)
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=2, tensorboard_log=str(tmp_path / "tb"), device="auto", **SMALL)
    assert model.device.type in ("cpu", "cuda")
    model.learn(200, callback=[eval_callback, checkpoint], progress_bar=True)
    assert (tmp_path / "eval" / "evaluations.npz").exists()
    assert sorted(p.name for p in (tmp_path / "ckpt").iterdir()) == [
        "rl_model_100_steps.zip",
        "rl_model_200_steps.zip",
        "rl_model_replay_buffer_100_steps.pkl",
        "rl_model_replay_buffer_200_steps.pkl",
    ]
    assert list((tmp_path / "tb").glob("SOUP_1/events.out.tfevents.*"))
    mean_reward, _ = evaluate_policy(model, eval_env, n_eval_episodes=1)
    assert np.isfinite(mean_reward)


def test_stochastic_predict_adds_no_noise_as_td3s():
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=2)
    obs = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    # the adaptive strategy explores with the weights it acts greedily with: the same actions, no noise added
    assert np.array_equal(model.predict(obs, deterministic=False)[0], model.predict(obs, deterministic=True)[0])


def test_the_default_noise_is_a_constant_normal_noise_of_std_01():
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=2, **SMALL)
    assert isinstance(model.action_noise, DecayingNormalActionNoise) and model.action_noise.decay == 1.0
    np.testing.assert_array_equal(model.action_noise.sigma, [0.1])
    model.learn(SMALL["learning_starts"] + 10)
    assert model.action_noise.n_calls == 10  # none during the random warm-up
    np.testing.assert_array_equal(model.action_noise.sigma, [0.1])
    assert model.logger.name_to_value["train/noise_std"] == 0.1


def test_noise_std_decays_per_draw_down_to_its_floor():
    noise = DecayingNormalActionNoise(np.zeros(1), np.full(1, 0.4), decay=0.99, sigma_min=0.1)
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=2, action_noise=noise, **SMALL)
    model.learn(60)  # 10 draws after the warm-up, none in it
    assert model.action_noise is noise and noise.sigma[0] == pytest.approx(max(0.1, 0.4 * 0.99**10))
    model.learn(200, reset_num_timesteps=False)  # reset() at the episodes' ends leaves the schedule where it is
    assert noise.sigma[0] == pytest.approx(0.1) and noise.n_calls == 210


def test_the_decaying_noise_draws_what_numpy_draws():
    noise = DecayingNormalActionNoise(np.zeros(2), np.full(2, 0.2), decay=0.5, sigma_min=0.06)
    np.random.seed(0)
    draws = np.stack([noise() for _ in range(3)])
    np.random.seed(0)
    expected = np.stack([np.random.normal(0.0, std, size=2) for std in (0.2, 0.1, 0.06)])
    assert draws.dtype == np.float64 and np.array_equal(draws, expected)
    noise.reset()
    assert noise.n_calls == 3  # reset() is the end of an episode, not of the schedule
    with pytest.raises(ValueError, match=re.escape("decay must be a float in (0, 1] (the noise std's decay per draw)")):
        DecayingNormalActionNoise(np.zeros(1), np.ones(1), decay=1.5)
    with pytest.raises(ValueError, match=re.escape("sigma_min must be a float in [0, inf)")):
        DecayingNormalActionNoise(np.zeros(1), np.ones(1), sigma_min=-0.1)
    with pytest.raises(ValueError, match=re.escape("sigma must be finite and >= 0")):
        DecayingNormalActionNoise(np.zeros(1), -np.ones(1))


def test_non_box_action_spaces_are_refused():
    with pytest.raises(AssertionError, match="only supports"):
        SOUP("MlpPolicy", "CartPole-v1")


@pytest.mark.parametrize(
    "kwargs, parameter",
    [
        (dict(n_heads=0), "n_heads"),
        (dict(n_heads=2.5), "n_heads"),
        (dict(n_actor_heads=3, n_critic_heads=2), "n_actor_heads"),
        (dict(mask_prob=0.0), "mask_prob"),
        (dict(mask_prob=1.2), "mask_prob"),
        (dict(confidence="fixed", confidence_kwargs=dict(alpha=1.0)), "alpha"),
        (dict(confidence="fixed", confidence_kwargs=dict(alpha=0.0)), "alpha"),
        (dict(confidence="decayed", confidence_kwargs=dict(decay=0.0)), "decay"),
        (dict(confidence_kwargs=dict(temperature=0.0)), "temperature"),
        (dict(confidence_kwargs=dict(lr=-1.0)), "lr"),
        (dict(confidence="sometimes"), "confidence"),
        (dict(confidence=42), "confidence"),
        (dict(preset="td3"), "preset"),
        (dict(preset="dbddpg", confidence="adaptive"), "preset"),
        (dict(train_heads="some"), "train_heads"),
        (dict(policy_kwargs=dict(net_arch="big")), "net_arch"),
        (dict(policy_kwargs=dict(net_arch=dict(qf_body=[64]))), "qf_body"),
        (dict(policy_kwargs=dict(net_arch=dict(pi=[64]))), "net_arch"),
        (dict(confidence="fixed", n_actor_heads=1, n_critic_heads=3, preset=None), None),
    ],
)
def test_invalid_arguments_name_the_parameter(kwargs, parameter):
    if parameter is None:  # a valid combination, for contrast
        SOUP("MlpPolicy", "Pendulum-v1", **kwargs)
        return
    with pytest.raises(ValueError, match=parameter):
        SOUP("MlpPolicy", "Pendulum-v1", **kwargs)


def test_preset_names_are_forgiving_and_explicit_settings_must_agree():
    model = SOUP("MlpPolicy", "Pendulum-v1", preset="MA-BDDPG", n_heads=4)
    assert (model.n_actor_heads, model.n_critic_heads, model.confidence, model.preset) == (1, 4, "none", "ma_bddpg")
    assert SOUP("MlpPolicy", "Pendulum-v1", preset="ddpg").mask_prob == 1.0
    assert SOUP("MlpPolicy", "Pendulum-v1", preset="soup", confidence="adaptive").confidence == "adaptive"
    with pytest.raises(ValueError, match="preset='multi_ddpg' sets n_critic_heads=1"):
        SOUP("MlpPolicy", "Pendulum-v1", preset="multi_ddpg", n_critic_heads=3)


def test_non_finite_rewards_are_caught_at_the_step_they_appear():
    class NaNReward(gym.Wrapper):
        def step(self, action):
            obs, reward, terminated, truncated, info = self.env.step(action)
            return (
                obs,
                float("nan") if self.env.unwrapped._elapsed_steps_for_test == 30 else reward,
                terminated,
                truncated,
                info,
            )

    class Counter(gym.Wrapper):
        def step(self, action):
            self.env.unwrapped._elapsed_steps_for_test = getattr(self.env.unwrapped, "_elapsed_steps_for_test", 0) + 1
            return self.env.step(action)

    model = SOUP("MlpPolicy", NaNReward(Counter(gym.make("Pendulum-v1"))), n_heads=2, **SMALL)
    with pytest.raises(ValueError, match="non-finite reward"):
        model.learn(100)
    assert model.num_timesteps == 30
