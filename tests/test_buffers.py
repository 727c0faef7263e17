"""Bootstrapped replay buffers: one bool mask per head with each transition."""

import re

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.buffers import DictReplayBuffer, NStepReplayBuffer, ReplayBuffer

from sb3_soup import (
    SOUP,
    BootstrappedDictReplayBuffer,
    BootstrappedHerReplayBuffer,
    BootstrappedNStepReplayBuffer,
    BootstrappedReplayBuffer,
)
from sb3_soup.buffers import bootstrapped_buffer_class

OBS = spaces.Box(-1, 1, (3,), np.float32)
ACT = spaces.Box(-1, 1, (2,), np.float32)


def _fill(buffer, n_steps: int, n_envs: int) -> None:
    for step in range(n_steps):
        obs = np.full((n_envs, 3), step, dtype=np.float32)
        buffer.add(obs, obs + 1, np.zeros((n_envs, 2)), np.full(n_envs, step), np.zeros(n_envs), [{} for _ in range(n_envs)])


@pytest.mark.parametrize("n_envs", [1, 3])
def test_masks_have_the_right_shape_dtype_and_rate(n_envs):
    np.random.seed(0)
    buffer = BootstrappedReplayBuffer(4000, OBS, ACT, device="cpu", n_envs=n_envs, n_masks=5, mask_prob=0.3)
    _fill(buffer, 4000 // n_envs, n_envs)
    assert buffer.masks.dtype == np.bool_
    assert buffer.masks.shape == (4000 // n_envs, n_envs, 5)
    assert buffer.masks.mean() == pytest.approx(0.3, abs=0.02)
    samples = buffer.sample(512)
    assert samples.masks.shape == (512, 5) and samples.masks.dtype == th.bool


def test_sampled_masks_belong_to_the_sampled_transitions():
    np.random.seed(1)
    buffer = BootstrappedReplayBuffer(100, OBS, ACT, device="cpu", n_envs=2, n_masks=4, mask_prob=0.5)
    _fill(buffer, 50, 2)
    # make each stored mask readable from its transition: env e at step t gets the bits of (t + e) % 16
    for step in range(50):
        for env in range(2):
            buffer.masks[step, env] = [bool((step + env) >> bit & 1) for bit in range(4)]
            buffer.observations[step, env, 1] = env
    samples = buffer.sample(200)
    steps = samples.observations[:, 0].long()
    envs = samples.observations[:, 1].long()
    expected = th.stack([((steps + envs) >> bit) & 1 for bit in range(4)], dim=1).bool()
    assert th.equal(samples.masks, expected)


def test_mask_prob_one_keeps_everything():
    buffer = BootstrappedReplayBuffer(50, OBS, ACT, device="cpu", n_masks=3, mask_prob=1.0)
    _fill(buffer, 50, 1)
    assert buffer.masks.all()


def test_optimize_memory_usage_and_dict_observations():
    buffer = BootstrappedReplayBuffer(
        64, OBS, ACT, device="cpu", optimize_memory_usage=True, handle_timeout_termination=False, n_masks=2, mask_prob=0.5
    )
    _fill(buffer, 70, 1)
    samples = buffer.sample(32)
    assert th.equal(samples.next_observations, samples.observations + 1)
    assert samples.masks.shape == (32, 2)

    dict_space = spaces.Dict({"a": OBS, "b": spaces.Box(0, 1, (2,), np.float32)})
    dict_buffer = BootstrappedDictReplayBuffer(64, dict_space, ACT, device="cpu", n_envs=2, n_masks=3, mask_prob=0.5)
    for _ in range(10):
        obs = {"a": np.zeros((2, 3), np.float32), "b": np.ones((2, 2), np.float32)}
        dict_buffer.add(obs, obs, np.zeros((2, 2)), np.zeros(2), np.zeros(2), [{}, {}])
    samples = dict_buffer.sample(8)
    assert samples.masks.shape == (8, 3) and set(samples.observations) == {"a", "b"}


@pytest.mark.parametrize("kwargs", [dict(n_masks=0), dict(mask_prob=0.0), dict(mask_prob=1.5), dict(mask_prob="half")])
def test_bad_mask_arguments_are_refused(kwargs):
    name = next(iter(kwargs))
    with pytest.raises(ValueError, match=name):
        BootstrappedReplayBuffer(10, OBS, ACT, **{"n_masks": 2, "mask_prob": 0.5, **kwargs})


def test_replay_buffer_round_trip_keeps_the_masks(tmp_path):
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=4, mask_prob=0.5, learning_starts=50, batch_size=16, seed=0)
    model.learn(120)
    model.save_replay_buffer(tmp_path / "buffer")
    loaded = SOUP.load(SOUP("MlpPolicy", "Pendulum-v1", n_heads=4).save(tmp_path / "m") or tmp_path / "m")
    loaded.load_replay_buffer(tmp_path / "buffer")
    original, restored = model.replay_buffer, loaded.replay_buffer
    assert isinstance(restored, BootstrappedReplayBuffer)
    assert restored.pos == original.pos == 120 and restored.n_masks == 4 and restored.mask_prob == 0.5
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts", "masks"):
        assert np.array_equal(getattr(original, name), getattr(restored, name)), name
    assert 0.3 < restored.masks[:120].mean() < 0.7


# ---------------------------------------------------------------- which buffer SOUP builds

DICT_OBS = spaces.Dict({"observation": OBS, "achieved_goal": OBS, "desired_goal": OBS})


@pytest.mark.parametrize(
    "given, observation_space, n_steps, expected",
    [
        (None, OBS, 1, BootstrappedReplayBuffer),
        (None, DICT_OBS, 1, BootstrappedDictReplayBuffer),
        (None, OBS, 3, BootstrappedNStepReplayBuffer),
        (ReplayBuffer, OBS, 1, BootstrappedReplayBuffer),
        (DictReplayBuffer, DICT_OBS, 1, BootstrappedDictReplayBuffer),
        (HerReplayBuffer, DICT_OBS, 1, BootstrappedHerReplayBuffer),
        (NStepReplayBuffer, OBS, 1, BootstrappedNStepReplayBuffer),
        (BootstrappedHerReplayBuffer, DICT_OBS, 1, BootstrappedHerReplayBuffer),
    ],
)
def test_sb3s_buffer_classes_become_their_bootstrapped_versions(given, observation_space, n_steps, expected):
    kwargs: dict = {}
    assert bootstrapped_buffer_class(given, observation_space, n_steps, 0.9, kwargs) is expected
    assert kwargs == ({"n_steps": 3, "gamma": 0.9} if n_steps > 1 else {})  # SB3's n-step arguments, for the default


class MyReplayBuffer(ReplayBuffer):
    pass


class MyBootstrappedBuffer(BootstrappedReplayBuffer):
    pass


def test_other_buffer_classes_are_refused_with_the_accepted_ones():
    assert bootstrapped_buffer_class(MyBootstrappedBuffer, OBS) is MyBootstrappedBuffer  # a subclass of ours keeps masks
    accepted = (
        "replay_buffer_class must be None, one of SB3's ReplayBuffer, DictReplayBuffer, HerReplayBuffer, NStepReplayBuffer "
        "(SOUP uses their bootstrapped versions) or a subclass of sb3_soup.BootstrappedReplayBuffer, "
        "sb3_soup.BootstrappedDictReplayBuffer, sb3_soup.BootstrappedHerReplayBuffer, sb3_soup.BootstrappedNStepReplayBuffer "
        "(SOUP needs the bootstrap masks), got "
    )
    for given in (MyReplayBuffer, "ReplayBuffer", ReplayBuffer(10, OBS, ACT)):
        with pytest.raises(ValueError, match=re.escape(accepted)):
            SOUP("MlpPolicy", "Pendulum-v1", replay_buffer_class=given, buffer_size=100)
    with pytest.raises(ValueError, match=r"replay_buffer_class=DictReplayBuffer stores Dict observations.*is Box"):
        bootstrapped_buffer_class(DictReplayBuffer, OBS)
