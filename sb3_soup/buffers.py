"""
Bootstrapped replay buffers: every transition is stored with a K-vector of Bernoulli(``mask_prob``) masks
(Algorithm 1: "Sample bootstrapped mask m_t ~ M, store (s_t, a_t, s_t+1, r_t, m_t)").

Each of SB3's replay buffers has a bootstrapped version, which SOUP builds when given SB3's class
(:func:`bootstrapped_buffer_class`): ``ReplayBuffer`` -> :class:`BootstrappedReplayBuffer`, ``DictReplayBuffer`` ->
:class:`BootstrappedDictReplayBuffer`, ``HerReplayBuffer`` -> :class:`BootstrappedHerReplayBuffer` (a relabelled
transition keeps the masks of the transition it was made from) and ``NStepReplayBuffer`` ->
:class:`BootstrappedNStepReplayBuffer` (an n-step sample has the masks of its first transition, the one sampled).
The HER and n-step versions subclass SB3's buffers and reuse their sampling as it is.
"""

import warnings
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer, NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.type_aliases import DictReplayBufferSamples, TensorDict
from stable_baselines3.common.vec_env import VecNormalize
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

from sb3_soup.validation import integer, number, outside_stacklevel


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

    def __init__(self, *args: Any, n_masks: int = 1, mask_prob: float = 1.0, **kwargs: Any) -> None:
        """SB3's buffer's arguments, then the masks': ``n_masks`` per transition, each 1 with ``mask_prob``."""
        super().__init__(*args, **kwargs)
        self._init_masks(n_masks, mask_prob)

    def add(self, *args: Any, **kwargs: Any) -> None:
        self._store_masks()
        super().add(*args, **kwargs)  # type: ignore[misc]

    def _init_masks(self, n_masks: int, mask_prob: float) -> None:
        n_masks = integer(1, "the number of bootstrapped head pairs")("n_masks", n_masks)
        mask_prob = number(0.0, 1.0, True, False, "probability that a head sees a transition; 1 turns bootstrap off")(
            "mask_prob", mask_prob
        )
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


class BootstrappedHerReplayBuffer(_MaskStorage, HerReplayBuffer):
    """
    Hindsight Experience Replay (SB3's :class:`HerReplayBuffer`, see it for the other arguments) with a bool mask per
    head stored with each transition. A virtual transition (the stored one with a new goal and its recomputed reward)
    keeps the masks of the transition it was made from: relabelling changes the goal, not which heads see the
    experience. The sampling is SB3's, as it is (real transitions first, then the virtual ones).

    :param n_masks: number of masks per transition (number of bootstrapped heads K)
    :param mask_prob: probability that a head sees a transition; 1 turns bootstrapping off
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # The masks of the real and of the virtual part of the minibatch being sampled (only during sample)
        self._sampled_masks: dict[str, th.Tensor] = {}

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> BootstrappedDictReplayBufferSamples:  # type: ignore[override]
        """
        SB3's HER sample, with each transition's masks (a virtual transition has the masks of its source transition).

        :param batch_size: Number of element to sample
        :param env: Associated VecEnv to normalize the observations/rewards when sampling
        :return: Samples, real transitions first, then the virtual ones (as SB3's)
        """
        self._sampled_masks = {}
        try:
            samples = super().sample(batch_size, env)
            # HerReplayBuffer.sample concatenates the real samples, then the virtual ones
            masks = th.cat((self._sampled_masks["real"], self._sampled_masks["virtual"]))  # (B, K)
        finally:
            self._sampled_masks = {}
        return BootstrappedDictReplayBufferSamples(**samples._asdict(), masks=masks)

    def _get_real_samples(
        self, batch_indices: np.ndarray, env_indices: np.ndarray, env: VecNormalize | None = None
    ) -> DictReplayBufferSamples:
        self._sampled_masks["real"] = self.to_torch(self.masks[batch_indices, env_indices])
        return super()._get_real_samples(batch_indices, env_indices, env)

    def _get_virtual_samples(
        self, batch_indices: np.ndarray, env_indices: np.ndarray, env: VecNormalize | None = None
    ) -> DictReplayBufferSamples:
        # The source transitions' masks: the new goal is sampled from their episodes, the masks stay theirs
        self._sampled_masks["virtual"] = self.to_torch(self.masks[batch_indices, env_indices])
        return super()._get_virtual_samples(batch_indices, env_indices, env)


class BootstrappedNStepReplayBuffer(_MaskStorage, NStepReplayBuffer):
    """
    n-step returns (SB3's :class:`NStepReplayBuffer`, see it and :class:`ReplayBuffer` for the other arguments) with a
    bool mask per head stored with each transition. A sample has the masks of the first transition of its n-step
    sequence (the one sampled, whose observation and action it holds); its reward is the discounted sum of up to
    ``n_steps`` rewards and its ``discounts`` the ``gamma ** k`` of the value it bootstraps from (SB3's computation).

    :param n_steps: Number of steps to accumulate rewards for n-step returns
    :param gamma: Discount factor for future rewards
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
        n_steps: int = 3,
        gamma: float = 0.99,
        n_masks: int = 1,
        mask_prob: float = 1.0,
    ):
        # SB3's NStepReplayBuffer fails on these without naming n_steps
        n_steps = integer(1, "steps of the n-step returns")("n_steps", n_steps)
        if optimize_memory_usage:
            raise ValueError(
                "optimize_memory_usage=True is not supported with n-step returns (SB3's NStepReplayBuffer does not support "
                "it): pass optimize_memory_usage=False, or n_steps=1"
            )
        super().__init__(
            buffer_size,
            observation_space,
            action_space,
            device,
            n_envs,
            optimize_memory_usage,
            handle_timeout_termination,
            n_steps=n_steps,
            gamma=gamma,
            n_masks=n_masks,
            mask_prob=mask_prob,
        )

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> BootstrappedReplayBufferSamples:  # type: ignore[override]
        # NStepReplayBuffer._get_samples first draws each sample's env, np.random.randint(0, n_envs, size=batch_inds.shape),
        # and does not return it: the same draw, made on the same generator state, gives the envs of its samples
        state = np.random.get_state()
        env_indices = np.random.randint(0, self.n_envs, size=batch_inds.shape)
        np.random.set_state(state)
        samples = super()._get_samples(batch_inds, env)
        return BootstrappedReplayBufferSamples(
            **samples._asdict(),
            masks=self.to_torch(self.masks[batch_inds, env_indices]),  # (B, K), the first transition's
        )


BOOTSTRAPPED_BUFFERS: dict[type[ReplayBuffer], type[ReplayBuffer]] = {
    ReplayBuffer: BootstrappedReplayBuffer,
    DictReplayBuffer: BootstrappedDictReplayBuffer,
    HerReplayBuffer: BootstrappedHerReplayBuffer,
    NStepReplayBuffer: BootstrappedNStepReplayBuffer,
}
"""SB3's replay buffer classes and the bootstrapped versions SOUP builds for them."""

_BOOTSTRAPPED_CLASSES = tuple(BOOTSTRAPPED_BUFFERS.values())
_GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")


def is_bootstrapped_buffer(buffer: Any) -> bool:
    """:return: whether ``buffer`` is one of the bootstrapped replay buffers (which store the masks SOUP needs)"""
    return isinstance(buffer, _BOOTSTRAPPED_CLASSES)


def load_bootstrapped_buffer(path: Any, n_masks: int, n_envs: int, verbose: int = 0) -> ReplayBuffer:
    """
    Read a replay buffer saved by ``model.save_replay_buffer`` and check that it fits a model: a bootstrapped buffer
    with masks for ``n_masks`` head pairs, filled by ``n_envs`` envs.

    :param path: the pickled buffer (a path or a file-like)
    :param n_masks: the model's head pairs
    :param n_envs: the model's envs
    :param verbose: SB3's verbosity of ``load_from_pkl``
    :return: the buffer
    :raises ValueError: for a truncated or corrupt file, or a buffer that does not fit
    """
    from stable_baselines3.common.save_util import load_from_pkl

    try:
        buffer = load_from_pkl(path, verbose)
    except OSError:
        raise
    except Exception as error:
        raise ValueError(
            f"could not read the replay buffer {path}: the file is truncated or corrupt (a process killed while writing "
            f"it leaves such files): {type(error).__name__}: {error}"
        ) from error
    if not is_bootstrapped_buffer(buffer):
        names = ", ".join(cls.__name__ for cls in _BOOTSTRAPPED_CLASSES)
        raise ValueError(
            f"{path} holds a {type(buffer).__name__}, not one of sb3_soup's bootstrapped replay buffers ({names}): SOUP "
            "needs the bootstrap masks"
        )
    if buffer.n_masks != n_masks:
        raise ValueError(
            f"the replay buffer in {path} has bootstrap masks for {buffer.n_masks} head pairs, this model has {n_masks}"
        )
    if buffer.n_envs != n_envs:
        raise ValueError(f"the replay buffer in {path} was filled by {buffer.n_envs} envs, this model has {n_envs}")
    return buffer


def _accepted() -> str:
    sb3 = ", ".join(cls.__name__ for cls in BOOTSTRAPPED_BUFFERS)
    ours = ", ".join(f"sb3_soup.{cls.__name__}" for cls in _BOOTSTRAPPED_CLASSES)
    return f"None, one of SB3's {sb3} (SOUP uses their bootstrapped versions) or a subclass of {ours}"


def bootstrapped_buffer_class(
    replay_buffer_class: Any,
    observation_space: spaces.Space,
    n_steps: int = 1,
    gamma: float = 0.99,
    replay_buffer_kwargs: dict[str, Any] | None = None,
) -> type[ReplayBuffer]:
    """
    SB3's choice of the replay buffer (``OffPolicyAlgorithm._setup_model``), bootstrapped: the class of SOUP's replay
    buffer, which stores the masks. ``None`` gives SB3's default for the observation space and ``n_steps`` (Dict
    observations: :class:`BootstrappedDictReplayBuffer`; ``n_steps > 1``: :class:`BootstrappedNStepReplayBuffer`, with
    ``n_steps`` and ``gamma`` added to ``replay_buffer_kwargs``; else :class:`BootstrappedReplayBuffer`); one of SB3's
    classes gives its bootstrapped version. As SB3, it warns that ``n_steps`` is ignored when a class is given (unless it
    is an n-step buffer already set to ``n_steps``, as a loaded model's is).

    :param replay_buffer_class: what the user passed to SOUP (``None``: the default)
    :param observation_space: the env's observation space
    :param n_steps: SOUP's ``n_steps`` (n-step returns when > 1)
    :param gamma: the discount factor
    :param replay_buffer_kwargs: the buffer's keyword arguments, updated in place with ``n_steps`` and ``gamma`` when the
        default buffer is an n-step one
    :return: the class of SOUP's replay buffer
    """
    is_dict = isinstance(observation_space, spaces.Dict)
    if replay_buffer_class is None:
        if is_dict:
            if n_steps > 1:
                raise ValueError(
                    f"n_steps={n_steps}: n-step returns are not supported for Dict observation spaces (as in SB3): "
                    "pass n_steps=1"
                )
            return BootstrappedDictReplayBuffer
        if n_steps > 1:
            if replay_buffer_kwargs is not None:
                replay_buffer_kwargs.update(n_steps=n_steps, gamma=gamma)
            return BootstrappedNStepReplayBuffer
        return BootstrappedReplayBuffer
    sb3_class = (ours for sb3, ours in BOOTSTRAPPED_BUFFERS.items() if replay_buffer_class is sb3)
    buffer_class = next(sb3_class, replay_buffer_class)
    if not (isinstance(buffer_class, type) and issubclass(buffer_class, _BOOTSTRAPPED_CLASSES)):
        raise ValueError(
            f"replay_buffer_class must be {_accepted()} (SOUP needs the bootstrap masks), got {replay_buffer_class!r}"
        )
    wants_dict = issubclass(buffer_class, DictReplayBuffer)
    if wants_dict != is_dict:
        raise ValueError(
            f"replay_buffer_class={replay_buffer_class.__name__} stores "
            f"{'Dict' if wants_dict else 'flat (non-Dict)'} observations, the env's observation space is "
            f"{type(observation_space).__name__}: use "
            f"{'a Dict buffer (DictReplayBuffer, HerReplayBuffer)' if is_dict else 'ReplayBuffer or NStepReplayBuffer'}"
        )
    if issubclass(buffer_class, HerReplayBuffer):
        assert isinstance(observation_space, spaces.Dict)
        missing = [key for key in _GOAL_KEYS if key not in observation_space.spaces]
        if missing:
            raise ValueError(
                f"replay_buffer_class={replay_buffer_class.__name__} needs a goal-conditioned env, whose observations "
                f"have the keys {list(_GOAL_KEYS)}; the env's lack {missing}"
            )
    set_to_n_steps = issubclass(buffer_class, NStepReplayBuffer) and (replay_buffer_kwargs or {}).get("n_steps") == n_steps
    if n_steps > 1 and not set_to_n_steps:
        warnings.warn(
            f"`n_steps={n_steps}` is ignored because a custom `replay_buffer_class` "
            f"(`{replay_buffer_class.__name__}`) was passed: n-step returns are only set up "
            "automatically when `replay_buffer_class` is `None`. "
            "To use n-step returns with a custom replay buffer, configure it explicitly, e.g. "
            f'`replay_buffer_kwargs={{"n_steps": {n_steps}, "gamma": {gamma}}}`.',
            stacklevel=outside_stacklevel(),
        )
    return buffer_class
