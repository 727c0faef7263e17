"""
SOUP as a drop-in for SB3's TD3 and DDPG (issue 18): the scenarios of SB3's own off-policy tests (test_run,
test_save_load, test_callbacks, test_vec_normalize, test_dict_env, test_predict, test_deterministic, test_spaces,
test_train_eval_mode, test_cnn, test_custom_policy, test_tensorboard, test_identity), written for SOUP with SB3's
arguments as SB3's tests pass them: a script written for TD3 or DDPG runs unchanged when its class becomes SOUP.
"""

import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from gymnasium import spaces
from stable_baselines3 import TD3
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback, StopTrainingOnRewardThreshold
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import FakeImageEnv, IdentityEnvBox
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, NatureCNN
from stable_baselines3.common.utils import get_linear_fn
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_soup import SOUP, ObservationSpaceError
from sb3_soup.policies import parse_net_arch

# the budgets of SB3's tests, smaller: a few gradient steps on tiny networks
TINY = dict(learning_starts=20, batch_size=16, buffer_size=500, n_heads=3)


def n_parameters(module: th.nn.Module) -> int:
    return sum(parameter.numel() for parameter in module.parameters())


class MatrixActionEnv(gym.Env):
    """Box(-1, 1, (2, 2)) actions (SB3's test_spaces DummyMultidimensionalAction) and rewards that check their shape."""

    observation_space = spaces.Box(-1, 1, (3,), np.float32)
    action_space = spaces.Box(-1, 1, (2, 2), np.float32)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        assert np.shape(action) == (2, 2), np.shape(action)
        return self.observation_space.sample(), -float(np.square(action).sum()), False, False, {}


class FloatImageEnv(gym.Env):
    """Float images in [-10, 10] (SB3's test_cnn image-like input): not an image for SB3 unless normalize_images=False."""

    observation_space = spaces.Box(-10, 10, (1, 36, 36), np.float32)
    action_space = spaces.Box(-1, 1, (1,), np.float32)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


class BatchNormExtractor(BaseFeaturesExtractor):
    """Flatten, BatchNorm and Dropout (SB3's test_train_eval_mode FlattenBatchNormDropoutExtractor)."""

    def __init__(self, observation_space: spaces.Box):
        super().__init__(observation_space, int(np.prod(observation_space.shape)))
        self.batch_norm = th.nn.BatchNorm1d(self.features_dim)
        self.dropout = th.nn.Dropout(0.5)

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return self.dropout(self.batch_norm(th.flatten(observations, start_dim=1)))


# ----- net_arch: SB3's forms -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "net_arch, expected",
    [
        ([400, 300], dict(pi_body=[400], pi_head=[300], qf_body=[400], qf_head=[300], qf_action_layer=0)),
        ([64], dict(pi_body=[], pi_head=[64], qf_body=[], qf_head=[64], qf_action_layer=0)),
        ([], dict(pi_body=[], pi_head=[], qf_body=[], qf_head=[], qf_action_layer=0)),
        (dict(pi=[8, 4], qf=[8]), dict(pi_body=[8], pi_head=[4], qf_body=[], qf_head=[8], qf_action_layer=0)),
        (None, dict(pi_body=[256], pi_head=[128], qf_body=[256, 256], qf_head=[128], qf_action_layer=1)),
        (
            dict(qf_body=[32], qf_action_layer=0),  # SOUP's form, SB3's critic
            dict(pi_body=[256], pi_head=[128], qf_body=[32], qf_head=[128], qf_action_layer=0),
        ),
    ],
)
def test_net_arch_forms_map_onto_bodies_and_heads_by_one_rule(net_arch, expected):
    # every hidden layer but the last is the shared body, the last each head's; SB3's critic takes the action at its input
    assert parse_net_arch(net_arch) == expected
    assert parse_net_arch(parse_net_arch(net_arch)) == expected  # the parsed form (saved with the policy) reads back


@pytest.mark.parametrize("net_arch", [[], [4], [4, 4], dict(qf=[8], pi=[8, 4])])  # SB3's test_custom_offpolicy
def test_sb3_net_arch_forms_train(net_arch):
    model = SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=net_arch), train_freq=2, **TINY).learn(60)
    assert model.policy_kwargs == dict(net_arch=net_arch)
    assert np.isfinite(model.logger.name_to_value["train/critic_loss"])


@pytest.mark.parametrize("net_arch", [[16, 8], [8], []])
def test_one_head_with_a_list_net_arch_has_sb3s_networks(net_arch):
    # K=1 with SB3's form: the actor and the critic are TD3's (n_critics=1), layer for layer
    soup = SOUP("MlpPolicy", "Pendulum-v1", preset="ddpg", n_heads=1, policy_kwargs=dict(net_arch=net_arch))
    td3 = TD3("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=net_arch, n_critics=1))
    assert n_parameters(soup.actor) == n_parameters(td3.actor)
    assert n_parameters(soup.critic) == n_parameters(td3.critic)
    obs = th.zeros(7, 3)
    assert soup.critic(obs, th.zeros(7, 1), head=0).shape == td3.critic(obs, th.zeros(7, 1))[0].shape == (7, 1)


def test_the_default_net_arch_is_the_papers():
    model = SOUP("MlpPolicy", "Pendulum-v1")
    assert model.policy.net_arch == dict(pi_body=[256], pi_head=[128], qf_body=[256, 256], qf_head=[128], qf_action_layer=1)
    assert model.policy_kwargs == {}
    # the action joins the critic at its second layer
    assert model.critic.obs_layer is not None and model.critic.obs_layer.in_features == 3
    assert model.critic.joint_layer is not None and model.critic.joint_layer.in_features == 256 + 1


def test_scoring_candidates_matches_scoring_each_action_with_the_action_at_the_input():
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, policy_kwargs=dict(net_arch=[8, 8]))
    obs = th.randn(5, 3)
    candidates = model.actor(obs)  # (Ka, B, A)
    q_matrix = model.critic.q_matrix(obs, candidates)  # (B, Kc, Ka)
    for k in range(3):
        for i in range(3):
            th.testing.assert_close(q_matrix[:, i, k], model.critic(obs, candidates[k], head=i)[:, 0])


# ----- n_critics, policy_kwargs, load --------------------------------------------------------------------------------


def test_n_critics_1_is_each_critic_head_and_more_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[64], n_critics=1))  # SB3's test_run
    with pytest.warns(UserWarning, match=r"n_critics=2 is ignored.*3 critic heads.*target_q='min_pair'") as record:
        model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, policy_kwargs=dict(net_arch=[8], n_critics=2))
    assert model.policy.n_critic_heads == 3
    assert record[0].filename == __file__  # the warning points at the line that passed n_critics


def test_policy_kwargs_stay_as_given_and_load_accepts_them(tmp_path):
    policy_kwargs = dict(net_arch=[16], n_critics=1)
    model = SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=policy_kwargs, confidence="fixed", **TINY)
    assert model.policy_kwargs == policy_kwargs  # SOUP's own policy arguments are not added to them
    model.save(tmp_path / "model.zip")
    loaded = SOUP.load(tmp_path / "model.zip", policy_kwargs=dict(net_arch=[16], n_critics=1))
    assert loaded.policy_kwargs == policy_kwargs
    assert (loaded.policy.n_critic_heads, type(loaded.policy.confidence).__name__) == (3, "FixedConfidence")
    with pytest.raises(ValueError, match="The specified policy kwargs do not equal the stored policy kwargs"):
        SOUP.load(tmp_path / "model.zip", policy_kwargs=dict(net_arch=[32]))


def test_custom_optimizer_and_activation():  # SB3's test_custom_optimizer
    policy_kwargs = dict(optimizer_class=th.optim.AdamW, optimizer_kwargs=dict(weight_decay=0.0), net_arch=[16])
    model = SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=policy_kwargs, train_freq=2, **TINY).learn(60)
    assert isinstance(model.actor.optimizer, th.optim.AdamW) and isinstance(model.critic.optimizer, th.optim.AdamW)


@pytest.mark.parametrize(
    "optimizer_kwargs",
    [
        dict(amsgrad=True),
        dict(maximize=False, foreach=False),
        dict(fused=False),
        dict(weight_decay=1e-4, decoupled_weight_decay=True),
    ],
    ids=str,
)
def test_torch_adams_options_reach_soups_adam(optimizer_kwargs):  # the Zoo's policy_kwargs: optimizer_kwargs for TD3's Adam
    model = SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(optimizer_kwargs=optimizer_kwargs), **TINY).learn(40)
    for optimizer in (model.actor.optimizer, model.critic.optimizer):
        assert all(optimizer.defaults[key] == value for key, value in optimizer_kwargs.items())
        assert model._n_updates > 0 and all(state["n_steps"].max() > 0 for state in optimizer.state.values())


def test_an_integral_float_policy_delay_is_tds():  # TD3 takes policy_delay=2.0 (a YAML or a sampler's float)
    model = SOUP("MlpPolicy", "Pendulum-v1", policy_delay=2.0, **TINY)
    assert model.policy_delay == 2 and type(model.policy_delay) is int
    with pytest.raises(ValueError, match="policy_delay must be an integer >= 1"):
        SOUP("MlpPolicy", "Pendulum-v1", policy_delay=2.5, **TINY)


# ----- learning rates ------------------------------------------------------------------------------------------------


def test_one_learning_rate_drives_actor_and_critic():
    model = SOUP("MlpPolicy", "Pendulum-v1", learning_rate=3e-3, **TINY).learn(40)
    assert model.critic_learning_rate is None
    assert model.actor.optimizer.param_groups[0]["lr"] == model.critic.optimizer.param_groups[0]["lr"] == 3e-3


def test_a_learning_rate_schedule_drives_actor_and_critic():
    schedule = get_linear_fn(1e-3, 1e-4, 1.0)  # the Zoo's lin_1e-3 is such a schedule
    model = SOUP("MlpPolicy", "Pendulum-v1", learning_rate=schedule, **TINY).learn(60)
    lr = model.actor.optimizer.param_groups[0]["lr"]
    assert lr < 1e-3 and model.critic.optimizer.param_groups[0]["lr"] == lr
    assert model.logger.name_to_value["train/critic_learning_rate"] == model.logger.name_to_value["train/learning_rate"]


def test_an_explicit_critic_learning_rate_is_kept():
    model = SOUP("MlpPolicy", "Pendulum-v1", learning_rate=1e-4, critic_learning_rate=3e-4, **TINY).learn(40)
    assert model.actor.optimizer.param_groups[0]["lr"] == 1e-4 and model.critic.optimizer.param_groups[0]["lr"] == 3e-4


def test_a_zero_learning_rate_freezes_the_critic():  # SB3's test_cnn sets model.lr_schedule on a built model
    model = SOUP("MlpPolicy", "Pendulum-v1", mask_prob=1.0, **TINY).learn(30)
    before = [parameter.clone() for parameter in model.critic.parameters()]
    model.lr_schedule = lambda _: 0.0
    model.train(gradient_steps=1, batch_size=16)
    for parameter, old in zip(model.critic.parameters(), before, strict=True):
        assert th.equal(parameter, old)


# ----- exploration noise ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("noise_class", [NormalActionNoise, OrnsteinUhlenbeckActionNoise])
def test_action_noise_is_sb3s(noise_class):  # SB3's test_deterministic_pg
    action_noise = noise_class(np.zeros(1), 0.1 * np.ones(1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model = SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[64, 64]), action_noise=action_noise, **TINY)
    model.learn(50)
    assert model.action_noise is action_noise
    assert "train/noise_std" not in model.logger.name_to_value  # logged for a DecayingNormalActionNoise (the default)


# ----- spaces --------------------------------------------------------------------------------------------------------


def test_matrix_shaped_actions_train_predict_and_view():  # SB3's test_action_spaces with a (2, 2) Box
    noise = NormalActionNoise(np.zeros((2, 2)), 0.1 * np.ones((2, 2)))
    for action_noise in (None, noise):
        model = SOUP("MlpPolicy", MatrixActionEnv(), action_noise=action_noise, **TINY).learn(50)
        assert model.replay_buffer.actions.shape[1:] == (1, 4)  # stored flat, as SB3 stores them
        assert model.predict(np.zeros(3, np.float32))[0].shape == (2, 2)
        assert model.predict(np.zeros((4, 3), np.float32), deterministic=True)[0].shape == (4, 2, 2)
        view = model.policy.ensemble_view(np.zeros((4, 3), np.float32))
        assert view.actions.shape == (4, 2, 2) and view.candidates.shape == (4, 3, 2, 2)


@pytest.mark.parametrize("net_arch", [[], [8, 8]])
def test_onnx_export_of_matrix_actions_and_sb3_critics(tmp_path, net_arch):
    ort = pytest.importorskip("onnxruntime")
    from sb3_soup import export_onnx

    model = SOUP("MlpPolicy", MatrixActionEnv(), n_heads=3, policy_kwargs=dict(net_arch=net_arch))
    export_onnx(model, tmp_path / "model.onnx")
    session = ort.InferenceSession(str(tmp_path / "model.onnx"), providers=["CPUExecutionProvider"])
    obs = np.random.default_rng(0).uniform(-1, 1, (4, 3)).astype(np.float32)
    (actions,) = session.run(None, {"obs": obs})
    np.testing.assert_allclose(actions, model.predict(obs, deterministic=True)[0], atol=1e-5)


@pytest.mark.parametrize("action_dtype", [np.float32, np.float64])
@pytest.mark.parametrize("dict_obs", [False, True])
def test_float64_spaces(action_dtype, dict_obs):  # SB3's test_float64_action_space
    box = spaces.Box(-1, 1, (2,), np.float64)
    env = gym.make("Pendulum-v1")
    env.action_space = spaces.Box(-2, 2, (1,), action_dtype)
    if dict_obs:
        dict_space = spaces.Dict({"a": box, "b": box})
        env = gym.wrappers.TransformObservation(env, lambda obs: {"a": obs[:2], "b": obs[2:]}, dict_space)
    policy = "MultiInputPolicy" if dict_obs else "MlpPolicy"
    model = SOUP(policy, env, policy_kwargs=dict(net_arch=[12]), **TINY).learn(40)
    action, _ = model.predict(env.observation_space.sample(), deterministic=False)
    assert action.dtype == action_dtype


class ObservationSpaceEnv(gym.Env):
    """Observations of any space, Box actions (SB3's test_spaces / test_dict_env observation spaces)."""

    action_space = spaces.Box(-1, 1, (1,), np.float32)

    def __init__(self, observation_space: spaces.Space):
        self.observation_space = observation_space

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), float(action[0]), False, False, {}


@pytest.mark.parametrize(
    "observation_space",
    [
        spaces.Discrete(4),
        spaces.MultiDiscrete([2, 3]),
        spaces.MultiBinary(3),
        spaces.Dict({"d": spaces.Discrete(3), "b": spaces.Box(-1, 1, (2,), np.float32), "m": spaces.MultiBinary(2)}),
    ],
    ids=["Discrete", "MultiDiscrete", "MultiBinary", "Dict"],
)
def test_observation_spaces(observation_space):  # the README's "Can I use?" table
    policy = "MultiInputPolicy" if isinstance(observation_space, spaces.Dict) else "MlpPolicy"
    model = SOUP(policy, ObservationSpaceEnv(observation_space), policy_kwargs=dict(net_arch=[8]), **TINY).learn(30)
    assert model.predict(observation_space.sample(), deterministic=True)[0].shape == (1,)


@pytest.mark.parametrize("action_space", [spaces.Discrete(2), spaces.MultiDiscrete([2, 2]), spaces.MultiBinary(2)])
def test_box_actions_only(action_space):  # as TD3: SB3's assertion on the action space
    env = ObservationSpaceEnv(spaces.Box(-1, 1, (2,), np.float32))
    env.action_space = action_space
    with pytest.raises(AssertionError, match="only supports"):
        SOUP("MlpPolicy", env)


def test_dict_observations_with_vec_normalize():  # SB3's test_dict_env test_vec_normalize
    box = spaces.Box(-1, 1, (2,), np.float32)

    def make_env():
        env = gym.make("Pendulum-v1")
        space = spaces.Dict({"a": box, "b": spaces.Box(-8, 8, (1,), np.float32)})
        return gym.wrappers.TransformObservation(env, lambda obs: {"a": obs[:2], "b": obs[2:]}, space)

    env = VecNormalize(DummyVecEnv([make_env]), norm_obs_keys=["a", "b"], gamma=0.99)
    model = SOUP("MultiInputPolicy", env, policy_kwargs=dict(net_arch=[8]), gamma=0.99, **TINY).learn(40)
    assert model.get_vec_normalize_env() is env
    assert model.predict(env.reset(), deterministic=True)[0].shape == (1, 1)


def test_offpolicy_normalization(tmp_path):  # SB3's test_vec_normalize test_offpolicy_normalization
    env = VecNormalize(DummyVecEnv([lambda: gym.make("Pendulum-v1")]), gamma=0.99)
    eval_env = VecNormalize(DummyVecEnv([lambda: gym.make("Pendulum-v1")]), training=False, norm_reward=False)
    model = SOUP("MlpPolicy", env, policy_kwargs=dict(net_arch=[16]), **TINY)
    model.learn(50, callback=EvalCallback(eval_env, eval_freq=25, n_eval_episodes=1, warn=False))
    # the eval env was synchronised with the training env's statistics
    np.testing.assert_allclose(eval_env.obs_rms.mean, env.obs_rms.mean)


def test_float_image_like_observations_with_normalize_images_false():  # SB3's test_image_like_input
    kwargs = dict(policy_kwargs=dict(normalize_images=False, features_extractor_kwargs=dict(features_dim=8)), **TINY)
    model = SOUP("CnnPolicy", FloatImageEnv(), **kwargs).learn(30)
    assert type(model.actor.features_extractor).__name__ == "NatureCNN"
    assert model.policy_kwargs["normalize_images"] is False


@pytest.mark.parametrize("model_class", [TD3, SOUP])
def test_cnn_policy_on_float_image_like_observations_raises_an_assertion_error(model_class):  # SB3's test_image_like_input
    # VecNormalize's float (1, 36, 36) observations are not images for NatureCNN unless normalize_images=False: TD3 fails
    # NatureCNN's assertion, SOUP raises ObservationSpaceError, both a ValueError and an AssertionError
    env = VecNormalize(DummyVecEnv([lambda: FakeImageEnv(36, 36, 1, discrete=False, channel_first=True)]))
    kwargs = dict(policy_kwargs=dict(normalize_images=True, features_extractor_kwargs=dict(features_dim=32)), seed=1)
    with pytest.raises(AssertionError, match="NatureCNN"):
        model_class("CnnPolicy", env, buffer_size=250, **kwargs)


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "discrete"])
def test_cnn_policy_on_non_image_observations_names_the_parameter(env_id):
    env = ObservationSpaceEnv(spaces.Discrete(4)) if env_id == "discrete" else env_id
    with pytest.raises(AssertionError):  # what TD3 raises
        TD3("CnnPolicy", env)
    with pytest.raises(ObservationSpaceError, match=r"^policy='CnnPolicy': NatureCNN .* takes image observations") as info:
        SOUP("CnnPolicy", env)
    assert isinstance(info.value, ValueError) and isinstance(info.value, AssertionError)
    assert "policy='MlpPolicy'" in str(info.value) and "normalize_images=False" in str(info.value)
    with pytest.raises(ObservationSpaceError, match=r"^policy_kwargs\['features_extractor_class'\]=NatureCNN: "):
        SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(features_extractor_class=NatureCNN))
    with pytest.raises(ObservationSpaceError, match="'MultiInputPolicy' is for Dict"):  # also both
        SOUP("MultiInputPolicy", "Pendulum-v1")


# ----- multiple envs, callbacks, TensorBoard, predict ----------------------------------------------------------------


def test_multi_env_with_action_noise_and_all_gradient_steps():  # SB3's test_offpolicy_multi_env
    env = make_vec_env(lambda: gym.wrappers.TimeLimit(gym.make("Pendulum-v1"), 50), n_envs=2)
    noise = NormalActionNoise(np.zeros(1), 0.1 * np.ones(1))  # SB3 makes it a VectorizedActionNoise
    kwargs = dict(policy_kwargs=dict(net_arch=[64], n_critics=1), action_noise=noise, buffer_size=1000, n_heads=3)
    SOUP("MlpPolicy", env, learning_starts=20, train_freq=5, **kwargs).learn(60)
    model = SOUP("MlpPolicy", env, learning_starts=0, train_freq=3, gradient_steps=-1, **kwargs).learn(30)
    evaluate_policy(model, env, n_eval_episodes=1, warn=False)


def test_callbacks(tmp_path):  # SB3's test_callbacks
    eval_env = gym.make("Pendulum-v1")
    callbacks = [
        CheckpointCallback(save_freq=20, save_path=str(tmp_path / "checkpoints"), save_replay_buffer=True),
        EvalCallback(
            eval_env, eval_freq=20, n_eval_episodes=1, warn=False, callback_on_new_best=StopTrainingOnRewardThreshold(1e9)
        ),
    ]
    model = SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[32]), **TINY)
    model.learn(60, callback=callbacks)
    assert (tmp_path / "checkpoints" / "rl_model_60_steps.zip").exists()
    assert (tmp_path / "checkpoints" / "rl_model_replay_buffer_60_steps.pkl").exists()
    SOUP.load(tmp_path / "checkpoints" / "rl_model_60_steps.zip").load_replay_buffer(
        tmp_path / "checkpoints" / "rl_model_replay_buffer_60_steps.pkl"
    )


def test_tensorboard(tmp_path):  # SB3's test_tensorboard
    model = SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8]), tensorboard_log=str(tmp_path), **TINY)
    model.learn(40)
    model.learn(40, reset_num_timesteps=False)
    assert (tmp_path / "SOUP_1").is_dir() and not (tmp_path / "SOUP_2").exists()


def test_predict_shapes():  # SB3's test_predict
    model = SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8]), **TINY)
    env = model.get_env()
    assert model.predict(env.observation_space.sample())[0].shape == (1,)
    assert model.predict(env.reset())[0].shape == (1, 1)
    assert model.predict(np.zeros((5, 3), np.float32), deterministic=True)[0].shape == (5, 1)
    with pytest.raises(ValueError):
        model.predict(np.zeros((5, 4), np.float32))  # SB3's error for an observation of another shape


def test_same_seed_same_training():  # SB3's test_deterministic_training_common
    def run() -> tuple[list, list]:
        noise = NormalActionNoise(np.zeros(1), 0.1 * np.ones(1))
        kwargs = dict(policy_kwargs=dict(net_arch=[64]), action_noise=noise, train_freq=4, **TINY)
        model = SOUP("MlpPolicy", "Pendulum-v1", seed=0, **kwargs).learn(60)
        env = model.get_env()
        obs = env.reset()
        actions, rewards = [], []
        for _ in range(20):
            action, _ = model.predict(obs, deterministic=False)
            obs, reward, _, _ = env.step(action)
            actions.append(action)
            rewards.append(reward)
        return actions, rewards

    first, second = run(), run()
    np.testing.assert_array_equal(first[0], second[0])
    np.testing.assert_array_equal(first[1], second[1])


# ----- state_dict, save/load -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("policy", ["MlpPolicy", "CnnPolicy"])
def test_save_load_policy_only(tmp_path, policy):  # SB3's test_save_load_policy, but for TD3's stand-alone actor
    if policy == "MlpPolicy":
        env, kwargs = IdentityEnvBox(-1, 1), dict(policy_kwargs=dict(net_arch=[16]), learning_rate=1e-3)
    else:  # SB3's CnnPolicy case, its arguments
        env = FakeImageEnv(screen_height=40, screen_width=40, n_channels=2, discrete=False)
        extractor = dict(features_extractor_kwargs=dict(features_dim=16))
        kwargs = dict(buffer_size=250, learning_starts=100, policy_kwargs=extractor, train_freq=2)
    env = DummyVecEnv([lambda: env])
    model = SOUP(policy, env, **kwargs).learn(128)
    env.reset()
    observations = np.concatenate([env.step([env.action_space.sample()])[0] for _ in range(10)], axis=0)
    policy_module = model.policy
    policy_module.load_state_dict({name: th.rand_like(value) for name, value in policy_module.state_dict().items()})
    actions, _ = policy_module.predict(observations, deterministic=True)
    policy_module.save(tmp_path / "policy.pkl")
    loaded = type(policy_module).load(tmp_path / "policy.pkl")
    for name, value in policy_module.state_dict().items():
        assert th.allclose(value, loaded.state_dict()[name]), name
    np.testing.assert_allclose(loaded.predict(observations, deterministic=True)[0], actions, atol=1e-4)
    # the one difference (docs/results.md, "Drop-in parity"): TD3's policy.actor is a stand-alone SB3 policy; SOUP's is
    # the K-head EnsembleActor, whose candidates the critic heads choose among in policy.predict
    assert not hasattr(policy_module.actor, "predict")


def test_every_state_dict_entry_is_a_float_and_averaging_loads(tmp_path):
    kwargs = dict(policy_kwargs=dict(net_arch=[8]), **TINY)
    models = [SOUP("MlpPolicy", "Pendulum-v1", seed=seed, **kwargs).learn(40) for seed in (0, 1)]
    state_dicts = [model.policy.state_dict() for model in models]
    assert all(value.is_floating_point() for value in state_dicts[0].values())
    assert float(state_dicts[0]["confidence.baseline_pending"]) == 0.0  # the baseline was set
    averaged = {key: (state_dicts[0][key] + state_dicts[1][key]) / 2 for key in state_dicts[0]}  # weight averaging
    models[0].policy.load_state_dict(averaged)
    # SB3's test_save_load: random values for every entry, then save/load gives them back exactly
    randomized = {key: th.rand_like(value) for key, value in state_dicts[1].items()}
    models[1].policy.load_state_dict(randomized)
    models[1].save(tmp_path / "model.zip")
    loaded = SOUP.load(tmp_path / "model.zip")
    for key, value in loaded.policy.state_dict().items():
        assert th.equal(value, randomized[key]), key


# ----- train/eval mode, identity env ---------------------------------------------------------------------------------


def test_collecting_rollouts_leaves_batch_norm_statistics():  # SB3's test_offpolicy_collect_rollout_batch_norm
    kwargs = dict(policy_kwargs=dict(net_arch=[16, 16], features_extractor_class=BatchNormExtractor), n_heads=3)
    model = SOUP("MlpPolicy", "Pendulum-v1", learning_starts=10, seed=1, gradient_steps=0, train_freq=1, **kwargs)
    networks = (model.actor, model.critic, model.actor_target, model.critic_target)
    before = [network.features_extractor.batch_norm.running_mean.clone() for network in networks]
    model.learn(40)
    for network, mean in zip(networks, before, strict=True):
        assert th.equal(network.features_extractor.batch_norm.running_mean, mean)
    # predict runs in evaluation mode: dropout off, same action twice
    obs = np.zeros((1, 3), np.float32)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


@pytest.mark.slow
def test_identity_env_box():  # SB3's test_identity test_continuous, at SB3's budget
    noise = NormalActionNoise(np.zeros(1), 0.1 * np.ones(1))
    kwargs = dict(policy_kwargs=dict(net_arch=[64, 64]), seed=0, gamma=0.95, action_noise=noise)
    model = SOUP("MlpPolicy", IdentityEnvBox(eps=0.5), learning_rate=1e-3, **kwargs).learn(400)
    evaluate_policy(model, IdentityEnvBox(eps=0.5), n_eval_episodes=20, reward_threshold=90, warn=False)


# ----- the RL Zoo's TD3 entry ----------------------------------------------------------------------------------------


def zoo_td3_entry(folder: Path) -> Path:
    """The Zoo's TD3 MuJoCo entry (td3.yml's Hopper-v4: net_arch [400, 300], normal noise of std 0.1), unchanged, as a
    config file for Pendulum-v1."""
    import rl_zoo3

    td3 = yaml.safe_load((Path(rl_zoo3.__file__).parent / "hyperparams" / "td3.yml").read_text())
    entry = td3["Hopper-v4"]
    assert entry["policy_kwargs"] == "dict(net_arch=[400, 300])"
    assert (entry["noise_type"], entry["noise_std"]) == ("normal", 0.1)
    conf = folder / "td3_entry.yml"
    conf.write_text(yaml.safe_dump({"Pendulum-v1": entry}))
    return conf


def test_zoo_td3_entry_builds_and_trains_soup(tmp_path):
    import argparse

    from rl_zoo3.exp_manager import ExperimentManager

    from sb3_soup import zoo

    zoo.register()
    # learning_starts: the entry's 10k random steps would leave a short run without a gradient step
    manager = ExperimentManager(
        argparse.Namespace(), "soup", "Pendulum-v1", str(tmp_path / "logs"), n_timesteps=120, eval_freq=-1,
        hyperparams=dict(learning_starts=100, batch_size=16), config=str(zoo_td3_entry(tmp_path)), seed=0, verbose=0,
        device="cpu",
    )  # fmt: skip
    setup = manager.setup_experiment()
    assert setup is not None
    model = setup[0]
    assert isinstance(model, SOUP) and model.policy_kwargs == dict(net_arch=[400, 300])
    assert model.policy.net_arch["pi_body"] == [400] and model.policy.net_arch["qf_head"] == [300]
    assert isinstance(model.action_noise, NormalActionNoise)
    model.learn(120)
    assert model._n_updates == 20


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_zoo_td3_entry_trains_with_soup_from_the_command_line(tmp_path):
    from test_zoo import check, run

    args = ["-m", "rl_zoo3.train", "--algo", "soup", "--env", "Pendulum-v1", "-conf", str(zoo_td3_entry(tmp_path))]
    args += ["-n", "300", "-f", "logs", "--hyperparams", "learning_starts:100", "--seed", "0"]
    result = check(run(args, tmp_path, timeout=900))
    assert "Applying normal noise with std 0.1" in result.stdout
    model = SOUP.load(tmp_path / "logs" / "soup" / "Pendulum-v1_1" / "Pendulum-v1.zip")
    assert model.policy_kwargs == dict(net_arch=[400, 300]) and model._n_updates == 200
