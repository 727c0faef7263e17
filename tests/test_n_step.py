"""
n-step returns as in SB3's TD3 (``n_steps``, ``NStepReplayBuffer``): SOUP's n-step samples carry the masks of the first
transition of their sequence, and the TD target bootstraps with each sample's discount (eq. 4:
``r + (1 - d) * discount * next_q``).
"""

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import TD3
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.env_util import make_vec_env

from sb3_soup import SOUP, BootstrappedNStepReplayBuffer, BootstrappedReplayBuffer

OBS = spaces.Box(-np.inf, np.inf, (2,), np.float32)
ACT = spaces.Box(-1, 1, (1,), np.float32)
TINY = dict(net_arch=dict(pi_body=[16], pi_head=[16], qf_body=[16, 16], qf_head=[16]))
SMALL = dict(learning_starts=50, batch_size=32, buffer_size=1000, policy_kwargs=TINY)


def _fill(buffer, n_adds: int, n_envs: int, rng: np.random.Generator) -> None:
    """Transitions that name themselves (observation = (step, env)), random rewards, terminations and truncations."""
    for step in range(n_adds):
        obs = np.stack([np.full(n_envs, step), np.arange(n_envs)], axis=1).astype(np.float32)
        dones = rng.random(n_envs) < 0.15
        infos = [{"TimeLimit.truncated": bool(done and rng.random() < 0.5)} for done in dones]
        buffer.add(obs, obs + 0.5, np.zeros((n_envs, 1)), rng.normal(size=n_envs), dones.astype(np.float32), infos)


@pytest.mark.parametrize("n_envs", [1, 3])
def test_n_step_samples_have_the_masks_of_their_first_transition_and_sb3s_returns(n_envs):
    kwargs = dict(device="cpu", n_envs=n_envs, n_steps=4, gamma=0.9)
    ours = BootstrappedNStepReplayBuffer(300, OBS, ACT, n_masks=6, mask_prob=0.5, **kwargs)
    sb3 = NStepReplayBuffer(300, OBS, ACT, **kwargs)
    for buffer in (ours, sb3):
        _fill(buffer, 130, n_envs, np.random.default_rng(0))  # buffer_size 300 // n_envs rows: wraps around for n_envs=3
    code = ours.observations[..., 0].astype(np.int64) * 3 + ours.observations[..., 1].astype(np.int64)  # (rows, n_envs)
    ours.masks[:] = (code[..., None] >> np.arange(6)) & 1  # each transition's masks readable from its observation

    np.random.seed(5)
    samples = ours.sample(500)
    np.random.seed(5)
    reference = sb3.sample(500)
    for name in ("observations", "actions", "next_observations", "dones", "rewards", "discounts"):
        assert th.equal(getattr(samples, name), getattr(reference, name)), name  # SB3's n-step computation, as it is
    first = samples.observations[:, 0].long() * 3 + samples.observations[:, 1].long()
    assert samples.masks.dtype == th.bool and samples.masks.shape == (500, 6)
    assert th.equal(samples.masks, ((first[:, None] >> th.arange(6)) & 1).bool())
    # the n-step sequences do not all stop at their first transition: their discounts are gamma ** 1..4
    assert set(np.round(np.log(samples.discounts.numpy().ravel()) / np.log(0.9)).astype(int)) == {1, 2, 3, 4}


def test_soup_n_steps_is_sb3s():
    env = make_vec_env("Pendulum-v1", n_envs=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing to warn about
        model = SOUP("MlpPolicy", env, n_steps=3, gamma=0.98, n_heads=3, seed=0, **SMALL)
    buffer = model.replay_buffer
    assert type(buffer) is BootstrappedNStepReplayBuffer and (buffer.n_steps, buffer.gamma) == (3, 0.98)
    assert (buffer.n_masks, buffer.mask_prob, buffer.n_envs) == (3, 0.5, 2)
    model.learn(150)
    assert buffer.sample(8).discounts.shape == (8, 1)
    one_step = SOUP("MlpPolicy", env, **SMALL)  # n_steps=1: one-step targets, the target's discount is gamma
    assert type(one_step.replay_buffer) is BootstrappedReplayBuffer
    assert one_step.learn(10).replay_buffer.sample(4).discounts is None
    TD3("MlpPolicy", env, n_steps=3, **{**SMALL, "policy_kwargs": dict(net_arch=[16])}).learn(60)  # the same arguments


def test_replay_buffer_class_n_step_replay_buffer_as_sb3_allows(tmp_path):
    kwargs = dict(replay_buffer_class=NStepReplayBuffer, replay_buffer_kwargs={"n_steps": 5, "gamma": 0.9}, **SMALL)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=2, seed=1, **kwargs)
    assert type(model.replay_buffer) is BootstrappedNStepReplayBuffer
    assert (model.replay_buffer.n_steps, model.replay_buffer.gamma) == (5, 0.9)
    model.learn(80)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # loading warns of nothing either
        loaded = SOUP.load(tmp_path / "model", env=make_vec_env("Pendulum-v1"))
        default = SOUP("MlpPolicy", "Pendulum-v1", n_steps=3, **SMALL)
        default.save(tmp_path / "default")
        SOUP.load(tmp_path / "default")
    assert type(loaded.replay_buffer) is BootstrappedNStepReplayBuffer and loaded.replay_buffer.n_steps == 5
    loaded.load_replay_buffer(tmp_path / "buffer")
    assert np.array_equal(loaded.replay_buffer.masks, model.replay_buffer.masks) and loaded.replay_buffer.pos == 80
    loaded.learn(40, reset_num_timesteps=False)


def test_n_steps_with_a_custom_replay_buffer_class_warns_as_sb3():
    for replay_buffer_class in (ReplayBuffer, BootstrappedReplayBuffer, NStepReplayBuffer):
        with pytest.warns(UserWarning, match=r"`n_steps=4` is ignored because a custom `replay_buffer_class`") as record:
            model = SOUP("MlpPolicy", "Pendulum-v1", n_steps=4, replay_buffer_class=replay_buffer_class, **SMALL)
        assert record[0].filename == __file__  # at the line that passed n_steps
        assert getattr(model.replay_buffer, "n_steps", 1) != 4  # (NStepReplayBuffer: its default, 3)


class DictPendulum(gym.ObservationWrapper):
    def __init__(self):
        super().__init__(gym.make("Pendulum-v1"))
        self.observation_space = spaces.Dict({"state": self.env.observation_space})

    def observation(self, observation):
        return {"state": observation}


@pytest.mark.parametrize(
    "kwargs, message",
    [
        # n_steps=0 is SB3's one-step TD (tests/test_bad_input.py); 2.0 is 2 (validation.py); SB3 fails on floats
        (dict(n_steps=2.5), r"n_steps must be an integer \(steps of the n-step returns"),
        (dict(n_steps=3, optimize_memory_usage=True, replay_buffer_kwargs=dict(handle_timeout_termination=False)),
         r"optimize_memory_usage=True is not supported with n-step returns"),
        (dict(replay_buffer_class=NStepReplayBuffer, replay_buffer_kwargs=dict(n_steps=-1)),
         r"n_steps must be an integer >= 1"),
    ],
)  # fmt: skip
def test_bad_n_step_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SOUP("MlpPolicy", "Pendulum-v1", **{**SMALL, **kwargs})


def test_n_step_returns_are_not_for_dict_observations_as_in_sb3():
    with pytest.raises(ValueError, match=r"n_steps=3: n-step returns are not supported for Dict observation spaces"):
        SOUP("MultiInputPolicy", DictPendulum(), n_steps=3, **SMALL)
    with pytest.raises(ValueError, match=r"replay_buffer_class=NStepReplayBuffer stores flat \(non-Dict\) observations"):
        SOUP("MultiInputPolicy", DictPendulum(), replay_buffer_class=NStepReplayBuffer, **SMALL)
