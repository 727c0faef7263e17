"""
Bootstrapped replay buffers: every transition is stored with a K-vector of Bernoulli(``mask_prob``) masks
(Algorithm 1: "Sample bootstrapped mask m_t ~ M, store (s_t, a_t, s_t+1, r_t, m_t)").
"""

from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer
from stable_baselines3.common.type_aliases import TensorDict
from stable_baselines3.common.vec_env import VecNormalize

from sb3_soup.validation import check


class BootstrappedReplayBufferSamples(NamedTuple):
    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor
    masks: th.Tensor  # (B, K) bool
    discounts: th.Tensor | None = None


class BootstrappedDictReplayBufferSamples(NamedTuple):
    observations: TensorDict
    actions: th.Tensor
    next_observations: TensorDict
    dones: th.Tensor
    rewards: th.Tensor
    masks: th.Tensor  # (B, K) bool
    discounts: th.Tensor | None = None


class _MaskStorage:
    """The mask part shared by the flat and the Dict bootstrapped buffers."""

    buffer_size: int
    n_envs: int
    pos: int
    masks: np.ndarray  # (buffer_size, n_envs, K) bool

    def _init_masks(self, n_masks: int, mask_prob: float) -> None:
        n_masks, mask_prob = check("n_masks", n_masks), check("mask_prob", mask_prob)
        self.n_masks = int(n_masks)
        self.mask_prob = float(mask_prob)
        self.masks = np.ones((self.buffer_size, self.n_envs, self.n_masks), dtype=bool)

    def _store_masks(self) -> None:
        """Draw the masks of the transitions being added at ``self.pos`` (call before ``pos`` moves on)."""
        if self.mask_prob < 1.0:
            self.masks[self.pos] = np.random.random((self.n_envs, self.n_masks)) < self.mask_prob
        else:
            self.masks[self.pos] = True

    def _sample_env_indices(self, batch_size: int) -> np.ndarray:
        # Same draw as SB3's ReplayBuffer._get_samples, kept so that masks come from the same transitions
        return np.random.randint(0, high=self.n_envs, size=(batch_size,))


class BootstrappedReplayBuffer(_MaskStorage, ReplayBuffer):
    """
    Replay buffer storing a bool mask per head with each transition (see :class:`ReplayBuffer` for the
    other arguments). Works with ``n_envs > 1``, ``optimize_memory_usage`` and timeout handling.

    :param n_masks: number of masks per transition (number of bootstrapped heads K)
    :param mask_prob: probability that a head sees a transition; 1 turns bootstrapping off
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        n_masks: int = 1,
        mask_prob: float = 1.0,
    ):
        super().__init__(
            buffer_size, observation_space, action_space, device, n_envs, optimize_memory_usage, handle_timeout_termination
        )
        self._init_masks(n_masks, mask_prob)

    def add(self, *args: Any, **kwargs: Any) -> None:
        self._store_masks()
        super().add(*args, **kwargs)

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> BootstrappedReplayBufferSamples:  # type: ignore[override]
        env_indices = self._sample_env_indices(len(batch_inds))
        if self.optimize_memory_usage:
            next_obs = self.observations[(batch_inds + 1) % self.buffer_size, env_indices, :]
        else:
            next_obs = self.next_observations[batch_inds, env_indices, :]
        dones = self.dones[batch_inds, env_indices] * (1 - self.timeouts[batch_inds, env_indices])
        return BootstrappedReplayBufferSamples(
            observations=self.to_torch(self._normalize_obs(self.observations[batch_inds, env_indices, :], env)),  # type: ignore[arg-type]
            actions=self.to_torch(self.actions[batch_inds, env_indices, :]),
            next_observations=self.to_torch(self._normalize_obs(next_obs, env)),  # type: ignore[arg-type]
            dones=self.to_torch(dones.reshape(-1, 1)),
            rewards=self.to_torch(self._normalize_reward(self.rewards[batch_inds, env_indices].reshape(-1, 1), env)),
            masks=self.to_torch(self.masks[batch_inds, env_indices]),  # (B, K)
        )


class BootstrappedDictReplayBuffer(_MaskStorage, DictReplayBuffer):
    """
    Dict-observation version of :class:`BootstrappedReplayBuffer`.

    :param n_masks: number of masks per transition (number of bootstrapped heads K)
    :param mask_prob: probability that a head sees a transition; 1 turns bootstrapping off
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Dict,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        n_masks: int = 1,
        mask_prob: float = 1.0,
    ):
        super().__init__(
            buffer_size, observation_space, action_space, device, n_envs, optimize_memory_usage, handle_timeout_termination
        )
        self._init_masks(n_masks, mask_prob)

    def add(self, *args: Any, **kwargs: Any) -> None:
        self._store_masks()
        super().add(*args, **kwargs)

    def _get_samples(  # type: ignore[override]
        self, batch_inds: np.ndarray, env: VecNormalize | None = None
    ) -> BootstrappedDictReplayBufferSamples:
        env_indices = self._sample_env_indices(len(batch_inds))
        obs = self._normalize_obs({key: obs[batch_inds, env_indices, :] for key, obs in self.observations.items()}, env)
        next_obs = self._normalize_obs(
            {key: obs[batch_inds, env_indices, :] for key, obs in self.next_observations.items()}, env
        )
        assert isinstance(obs, dict) and isinstance(next_obs, dict)
        dones = self.dones[batch_inds, env_indices] * (1 - self.timeouts[batch_inds, env_indices])
        return BootstrappedDictReplayBufferSamples(
            observations={key: self.to_torch(value) for key, value in obs.items()},
            actions=self.to_torch(self.actions[batch_inds, env_indices]),
            next_observations={key: self.to_torch(value) for key, value in next_obs.items()},
            dones=self.to_torch(dones.reshape(-1, 1)),
            rewards=self.to_torch(self._normalize_reward(self.rewards[batch_inds, env_indices].reshape(-1, 1), env)),
            masks=self.to_torch(self.masks[batch_inds, env_indices]),  # (B, K)
        )


def bootstrapped_buffer_class(replay_buffer_class: Any, observation_space: spaces.Space) -> type[ReplayBuffer]:
    """
    :param replay_buffer_class: what the user passed to SOUP (``None``: the default)
    :param observation_space: the env's observation space
    :return: the class of SOUP's replay buffer: a bootstrapped buffer (flat or Dict), which stores the masks
    """
    if replay_buffer_class is None:
        return BootstrappedDictReplayBuffer if isinstance(observation_space, spaces.Dict) else BootstrappedReplayBuffer
    if not (
        isinstance(replay_buffer_class, type)
        and issubclass(replay_buffer_class, (BootstrappedReplayBuffer, BootstrappedDictReplayBuffer))
    ):
        raise ValueError(
            "replay_buffer_class must be None or a subclass of sb3_soup.BootstrappedReplayBuffer or "
            f"BootstrappedDictReplayBuffer (SOUP needs the bootstrap masks), got {replay_buffer_class!r}"
        )
    return replay_buffer_class
