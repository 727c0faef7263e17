"""
Hindsight Experience Replay: a script written for SB3's DDPG/TD3 with ``HerReplayBuffer`` runs unchanged with SOUP, and
every relabelled (virtual) transition keeps the bootstrap masks of the transition it was made from.
"""

import warnings

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG, HerReplayBuffer
from stable_baselines3.common.buffers import DictReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import BitFlippingEnv
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_soup import SOUP, BootstrappedHerReplayBuffer
from sb3_soup.checkpoint import load_checkpoint, save_checkpoint

N_BITS = 4
TINY = dict(net_arch=dict(pi_body=[32], pi_head=[32], qf_body=[32, 32], qf_head=[32]))
HER = dict(replay_buffer_class=HerReplayBuffer, replay_buffer_kwargs=dict(n_sampled_goal=4, goal_selection_strategy="future"))
SMALL = dict(learning_starts=40, batch_size=32, buffer_size=2000, train_freq=4, gradient_steps=2, policy_kwargs=TINY)


def bit_flipping(n_envs: int = 1, n_bits: int = N_BITS, seed: int = 0):
    return make_vec_env(lambda: BitFlippingEnv(n_bits=n_bits, continuous=True), n_envs=n_envs, seed=seed)


def _filled_buffer(buffer_class, n_envs: int, n_steps: int = 60, **kwargs):
    """
    A HER buffer filled with BitFlippingEnv episodes whose stored actions name their transition: ``action[0]`` is the
    step, ``action[1]`` the env. Each transition's masks are then made readable from the same two numbers.
    """
    venv = bit_flipping(n_envs)
    buffer = buffer_class(
        1000, venv.observation_space, venv.action_space, env=venv, device="cpu", n_envs=n_envs, **kwargs
    )  # fmt: skip
    obs = venv.reset()
    for step in range(n_steps):
        next_obs, rewards, dones, infos = venv.step(np.stack([venv.action_space.sample() for _ in range(n_envs)]))
        stored_next = {key: value.copy() for key, value in next_obs.items()}
        for env, done in enumerate(dones):
            if done:
                stored_next_env = infos[env]["terminal_observation"]
                for key in stored_next:
                    stored_next[key][env] = stored_next_env[key]
        actions = np.zeros((n_envs, N_BITS), np.float32)
        actions[:, 0], actions[:, 1] = step, np.arange(n_envs)
        buffer.add(obs, stored_next, actions, rewards, dones, infos)
        obs = next_obs
    return buffer


def _readable_mask(steps: th.Tensor, envs: th.Tensor, n_masks: int) -> th.Tensor:
    code = steps * 3 + envs
    return th.stack([(code >> bit) & 1 for bit in range(n_masks)], dim=1).bool()  # (B, K)


# ---------------------------------------------------------------- the buffer


@pytest.mark.parametrize("goal_selection_strategy", ["future", "final", "episode"])
@pytest.mark.parametrize("n_envs", [1, 2])
def test_relabelled_transitions_keep_the_masks_of_their_source_transition(goal_selection_strategy, n_envs):
    np.random.seed(0)
    n_masks = 5
    buffer = _filled_buffer(
        BootstrappedHerReplayBuffer, n_envs, n_sampled_goal=4, goal_selection_strategy=goal_selection_strategy,
        n_masks=n_masks, mask_prob=0.5,
    )  # fmt: skip
    steps, envs = np.meshgrid(np.arange(buffer.pos), np.arange(n_envs), indexing="ij")  # (pos, n_envs) each
    masks = _readable_mask(th.as_tensor(steps.ravel()), th.as_tensor(envs.ravel()), n_masks)  # (pos * n_envs, K)
    buffer.masks[: buffer.pos] = masks.numpy().reshape(buffer.pos, n_envs, n_masks)
    samples = buffer.sample(400)
    n_virtual = int(buffer.her_ratio * 400)  # SB3: the real transitions first, then the virtual ones
    step, env = samples.actions[:, 0].long(), samples.actions[:, 1].long()
    assert samples.masks.shape == (400, n_masks) and samples.masks.dtype == th.bool
    assert th.equal(samples.masks, _readable_mask(step, env, n_masks))  # real and virtual alike
    # the virtual ones were relabelled: a goal of the episode's achieved goals, its reward recomputed
    stored_goals = th.as_tensor(buffer.observations["desired_goal"][step.numpy(), env.numpy()])
    relabelled = (samples.observations["desired_goal"] != stored_goals).any(dim=1)
    assert not relabelled[: 400 - n_virtual].any() and relabelled[400 - n_virtual :].sum() > 50
    assert th.equal(samples.observations["desired_goal"], samples.next_observations["desired_goal"])
    achieved = samples.next_observations["achieved_goal"]
    assert th.equal(samples.rewards[:, 0], -(achieved != samples.observations["desired_goal"]).any(dim=1).float())


def test_sampling_is_sb3s_her_sampling_with_masks():
    """Same transitions, same seed: the samples are those of SB3's HerReplayBuffer (its sampling is reused as it is)."""
    np.random.seed(1)
    ours = _filled_buffer(BootstrappedHerReplayBuffer, 2, n_sampled_goal=2, copy_info_dict=True, n_masks=3, mask_prob=0.5)
    np.random.seed(1)
    sb3 = _filled_buffer(HerReplayBuffer, 2, n_sampled_goal=2, copy_info_dict=True)
    for name in ("actions", "rewards", "dones", "timeouts", "ep_start", "ep_length"):
        assert np.array_equal(getattr(ours, name), getattr(sb3, name)), name
    np.random.seed(2)
    with_masks = ours.sample(64)
    np.random.seed(2)
    without = sb3.sample(64)
    for name in ("actions", "rewards", "dones"):
        assert th.equal(getattr(with_masks, name), getattr(without, name)), name
    for key in without.observations:
        assert th.equal(with_masks.observations[key], without.observations[key]), key
        assert th.equal(with_masks.next_observations[key], without.next_observations[key]), key
    assert with_masks.masks.shape == (64, 3) and with_masks.discounts is None


@pytest.mark.parametrize("handle_timeout_termination", [True, False])
def test_timeouts_of_bit_flipping_episodes(handle_timeout_termination):
    """BitFlippingEnv truncates its episodes after n_bits steps: bootstrapped through with handle_timeout_termination."""
    np.random.seed(3)
    buffer = _filled_buffer(
        BootstrappedHerReplayBuffer, 2, handle_timeout_termination=handle_timeout_termination, n_masks=2, mask_prob=0.5
    )
    stored = buffer.dones[: buffer.pos].astype(bool)
    truncated = buffer.timeouts[: buffer.pos].astype(bool)
    assert truncated.any() == handle_timeout_termination and (truncated <= stored).all()
    samples = buffer.sample(500)
    step, env = samples.actions[:, 0].long().numpy(), samples.actions[:, 1].long().numpy()
    expected = stored[step, env] & ~truncated[step, env]
    assert np.array_equal(samples.dones[:, 0].numpy().astype(bool), expected)


# ---------------------------------------------------------------- SOUP with HER


def test_soup_takes_sb3s_her_replay_buffer_as_ddpg_does():
    env = bit_flipping(n_envs=2)
    model = SOUP("MultiInputPolicy", env, n_heads=3, seed=0, **HER, **SMALL)
    assert type(model.replay_buffer) is BootstrappedHerReplayBuffer
    assert model.replay_buffer.n_masks == 3 and model.replay_buffer.mask_prob == 0.5
    assert model.replay_buffer.n_sampled_goal == 4 and model.replay_buffer.env is env
    model.learn(200)
    assert model.replay_buffer.masks[: model.replay_buffer.pos].shape == (100, 2, 3)
    assert 0.3 < model.replay_buffer.masks[: model.replay_buffer.pos].mean() < 0.7
    evaluate_policy(model, Monitor(BitFlippingEnv(n_bits=N_BITS, continuous=True)), n_eval_episodes=2)
    # the same script, DDPG's way
    DDPG("MultiInputPolicy", env, **HER, **{**SMALL, "policy_kwargs": dict(net_arch=[32])}).learn(100)


def _params(model):
    return th.nn.utils.parameters_to_vector(model.policy.parameters())


def test_save_load_of_a_her_model(tmp_path):
    env = bit_flipping(n_envs=2)
    model = SOUP("MultiInputPolicy", env, n_heads=3, seed=0, **HER, **SMALL)
    model.learn(120)
    obs = env.reset()
    model.save(tmp_path / "her")
    loaded = SOUP.load(tmp_path / "her", env=env)
    assert type(loaded.replay_buffer) is BootstrappedHerReplayBuffer and loaded.replay_buffer.env is env
    assert loaded.replay_buffer.n_sampled_goal == 4 and "env" not in loaded.replay_buffer_kwargs  # the env is not saved
    assert np.array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    loaded.learn(80)
    with pytest.raises(ValueError, match=r"HerReplayBuffer needs its env.*SOUP.load\(path, env=\.\.\.\)"):
        SOUP.load(tmp_path / "her")


@pytest.mark.parametrize("truncate_last_traj", [True, False])
def test_replay_buffer_round_trip_keeps_the_masks_and_the_episodes(tmp_path, truncate_last_traj):
    env = bit_flipping(n_envs=2)
    model = SOUP("MultiInputPolicy", env, n_heads=3, seed=0, **HER, **SMALL)
    model.learn(104)  # 13 rounds of train_freq=4 steps x 2 envs
    original = model.replay_buffer
    assert (original._current_ep_start != original.pos).any()
    model.save_replay_buffer(tmp_path / "buffer")

    fresh = SOUP("MultiInputPolicy", env, n_heads=3, seed=1, **HER, **SMALL)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fresh.load_replay_buffer(tmp_path / "buffer", truncate_last_traj=truncate_last_traj)
    truncation_warned = any("will be truncated" in str(warning.message) for warning in caught)
    assert truncation_warned == truncate_last_traj  # SB3's warning
    restored = fresh.replay_buffer
    assert type(restored) is BootstrappedHerReplayBuffer and restored.env is env and restored.pos == original.pos
    last = original.pos - 1
    for name in ("actions", "rewards", "masks", "ep_start"):
        assert np.array_equal(getattr(original, name), getattr(restored, name)), name
    for key in original.observations:
        assert np.array_equal(original.observations[key], restored.observations[key]), key
    assert np.array_equal(original.dones[:last], restored.dones[:last])
    if truncate_last_traj:  # the unfinished episodes end there (a timeout, to bootstrap through) and can be sampled
        assert restored.dones[last].all() and restored.timeouts[last].all() and (restored.ep_length[last] > 0).all()
        assert (restored._current_ep_start == restored.pos).all()
    else:  # the episodes go on
        assert np.array_equal(original.ep_length, restored.ep_length) and np.array_equal(original.dones, restored.dones)
    fresh.learn(60, reset_num_timesteps=truncate_last_traj)
    with pytest.raises(ValueError, match="bootstrap masks for 3 head pairs, this model has 2"):
        SOUP("MultiInputPolicy", env, n_heads=2, **HER, **SMALL).load_replay_buffer(tmp_path / "buffer")


class Actions(BaseCallback):
    def __init__(self):
        super().__init__()
        self.actions: list[np.ndarray] = []

    def _on_step(self) -> bool:
        self.actions.append(self.locals["actions"].copy())
        return True


def test_a_her_checkpoint_resumes_the_same_episodes(tmp_path):
    """An exact resume continues the unfinished episodes: its HER buffer is not truncated (SB3's truncate_last_traj)."""
    kwargs = dict(n_heads=2, seed=4, **HER, **SMALL)
    reference, recorded = SOUP("MultiInputPolicy", bit_flipping(2), **kwargs), Actions()
    reference.learn(184, callback=recorded)
    interrupted = SOUP("MultiInputPolicy", bit_flipping(2), **kwargs)
    interrupted.learn(104)  # 13 rounds of train_freq=4 steps x 2 envs
    assert (interrupted.replay_buffer._current_ep_start != interrupted.replay_buffer.pos).any()  # in mid-episode
    files = save_checkpoint(interrupted, tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # no truncation warning
        resumed = load_checkpoint(files, bit_flipping(2))
    continued = Actions()
    resumed.learn(80, callback=continued, reset_num_timesteps=False)
    assert np.array_equal(np.concatenate(continued.actions), np.concatenate(recorded.actions[52:]))
    assert th.equal(_params(resumed), _params(reference))


# ---------------------------------------------------------------- bad input


class NotAGoalEnv(BitFlippingEnv):
    def __init__(self):
        super().__init__(n_bits=N_BITS, continuous=True)
        self.observation_space = spaces.Dict({"observation": self.observation_space["observation"]})

    def _get_obs(self):
        return {"observation": super()._get_obs()["observation"]}


class MyHerBuffer(HerReplayBuffer):
    pass


@pytest.mark.parametrize(
    "env, replay_buffer_class, message",
    [
        (lambda: NotAGoalEnv(), HerReplayBuffer, r"needs a goal-conditioned env.*lack \['achieved_goal', 'desired_goal'\]"),
        (lambda: BitFlippingEnv(continuous=True), MyHerBuffer, r"replay_buffer_class must be None, one of SB3's ReplayBuffer"),
        ("Pendulum-v1", HerReplayBuffer, r"stores Dict observations, the env's observation space is Box"),
        (lambda: BitFlippingEnv(continuous=True), DictReplayBuffer, None),  # accepted: plain replay, no relabelling
    ],
)
def test_her_needs_a_goal_conditioned_env(env, replay_buffer_class, message):
    policy = "MlpPolicy" if env == "Pendulum-v1" else "MultiInputPolicy"
    vec_env = env if isinstance(env, str) else make_vec_env(env)
    if message is None:
        model = SOUP(policy, vec_env, replay_buffer_class=replay_buffer_class, **SMALL)
        assert not isinstance(model.replay_buffer, HerReplayBuffer)
    else:
        with pytest.raises(ValueError, match=message):
            SOUP(policy, vec_env, replay_buffer_class=replay_buffer_class, **SMALL)


# ---------------------------------------------------------------- learning


@pytest.mark.slow
def test_soup_with_her_learns_bit_flipping_that_it_does_not_learn_without():
    """
    10 bits: a random policy reaches the goal in ~1% of its episodes; HER's relabelled goals make it learnable. (With 8
    bits, ~3%, SOUP's defaults since 0.2.0a0 learn it without HER too: 1.0 in 5000 steps.)
    """

    def train(**kwargs):
        env = bit_flipping(n_envs=1, n_bits=10, seed=0)
        model = SOUP("MultiInputPolicy", env, learning_starts=200, batch_size=128, gamma=0.95, seed=0, stats_window_size=50,
                     **kwargs)  # fmt: skip
        model.learn(5000)
        return np.mean(model.ep_success_buffer)

    assert train(**HER) > 0.7
    assert train() < 0.2
