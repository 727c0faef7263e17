"""
Exploration noise as SB3 models it, an ``ActionNoise``: :class:`DecayingNormalActionNoise`, a Gaussian noise whose std
decays per draw (the paper mode's schedule), and :func:`default_action_noise`, SOUP's noise when ``action_noise`` is
None. The RL Zoo's hyper-parameters express it as ``noise_type: 'decaying_normal'`` with ``noise_std``, ``noise_decay``
and ``noise_std_min`` (:func:`zoo_action_noise`, used by ``sb3_soup.zoo`` and the experiment runner).
"""

import math
from typing import Any

import numpy as np
from numpy.typing import DTypeLike
from stable_baselines3.common.noise import ActionNoise, NormalActionNoise, VectorizedActionNoise

from sb3_soup.validation import given, number

DEFAULT_NOISE_STD = 0.1
"""SOUP's exploration noise when ``action_noise`` is None: a constant N(0, 0.1), the RL Zoo's for TD3 and DDPG."""
DECAYING_NORMAL = "decaying_normal"
"""The noise type of the RL Zoo's hyper-parameters that :func:`zoo_action_noise` builds a decaying noise for."""
ZOO_NOISE_KEYS = ("noise_type", "noise_std", "noise_decay", "noise_std_min")


class DecayingNormalActionNoise(NormalActionNoise):
    """
    A Gaussian action noise whose std decays with each draw: the ``t``-th call (from 0) draws from
    ``N(mean, max(sigma_min, sigma * decay ** t))``. ``reset()``, which SB3 calls at the end of each episode, leaves the
    schedule where it is; the number of draws is pickled with the noise, so a model saved and loaded (or a checkpoint
    resumed) continues the schedule where it was.

    With ``n_envs > 1`` SB3 wraps it in a ``VectorizedActionNoise``, which deep-copies it once per env: each copy is
    called once per vectorised step, so the schedule then counts vectorised steps (``num_timesteps / n_envs``), the
    same for every env. SOUP draws no noise during the random warm-up (``learning_starts``): the schedule starts with
    the first step the ensemble acts.

    :param mean: mean of the noise (shaped as the action space)
    :param sigma: initial std of the noise, >= 0 (shaped as the action space)
    :param decay: multiplicative decay of the std per draw, in (0, 1] (1: constant)
    :param sigma_min: the std never goes below this, >= 0
    :param dtype: type of the output noise (float64: SOUP adds it to the float32 actions as NumPy's Gaussian draws are)
    """

    def __init__(
        self, mean: np.ndarray, sigma: np.ndarray, decay: float = 1.0, sigma_min: float = 0.0, dtype: DTypeLike = np.float64
    ) -> None:
        sigma = np.asarray(sigma, dtype=np.float64)
        if not (np.all(np.isfinite(sigma)) and np.all(sigma >= 0)):
            raise ValueError(f"sigma must be finite and >= 0 (the noise's initial std), {given(sigma)}")
        self.decay = number(0.0, 1.0, True, False, "the noise std's decay per draw")("decay", decay)
        self.sigma_min = number(0.0, math.inf, False, True, "the lowest noise std")("sigma_min", sigma_min)
        self.n_calls = 0
        super().__init__(np.asarray(mean, dtype=np.float64), sigma, dtype)

    @property
    def sigma(self) -> np.ndarray:
        """The std of the next draw."""
        return np.maximum(self.sigma_min, self._sigma * self.decay**self.n_calls)

    def __call__(self) -> np.ndarray:
        noise = np.random.normal(self._mu, self.sigma).astype(self._dtype)
        self.n_calls += 1
        return noise

    def __repr__(self) -> str:
        return (
            f"DecayingNormalActionNoise(mu={self._mu}, sigma={self._sigma}, decay={self.decay}, sigma_min={self.sigma_min}, "
            f"n_calls={self.n_calls})"
        )


def check_action_noise(name: str, value: Any) -> ActionNoise | None:
    """The rule of an ``action_noise`` argument: None (SOUP's N(0, 0.1)) or an SB3 ``ActionNoise``."""
    if value is not None and not isinstance(value, ActionNoise):
        raise ValueError(
            f"{name} must be None (SOUP's N(0, 0.1), see sb3_soup.noise.default_action_noise) or an instance of "
            f"stable_baselines3.common.noise.ActionNoise (e.g. sb3_soup.DecayingNormalActionNoise), got {value!r} "
            f"({type(value).__name__})"
        )
    return value


def default_action_noise(action_shape: tuple[int, ...]) -> DecayingNormalActionNoise:
    """
    :param action_shape: the action space's shape
    :return: SOUP's noise when ``action_noise`` is None, N(0, :data:`DEFAULT_NOISE_STD`) in the [-1, 1] action scale
    """
    return DecayingNormalActionNoise(np.zeros(action_shape), np.full(action_shape, DEFAULT_NOISE_STD))


def noise_std(action_noise: ActionNoise | None) -> float | None:
    """
    :param action_noise: a model's ``action_noise``
    :return: the mean std of its next draw when it is a :class:`DecayingNormalActionNoise` (or SB3's vectorized copies
        of one, whose schedules run together), else None
    """
    if isinstance(action_noise, VectorizedActionNoise):
        action_noise = action_noise.noises[0]
    if isinstance(action_noise, DecayingNormalActionNoise):
        return float(np.mean(action_noise.sigma))
    return None


def is_decaying_normal(hyperparams: dict[str, Any]) -> bool:
    """:return: whether RL-Zoo hyper-parameters ask for a decaying noise (``noise_type: 'decaying_normal'``)"""
    return str(hyperparams.get("noise_type") or "").strip() == DECAYING_NORMAL


def zoo_action_noise(hyperparams: dict[str, Any], action_shape: tuple[int, ...]) -> dict[str, Any]:
    """
    The RL Zoo's noise keys for a decaying noise: ``noise_type: 'decaying_normal'`` with ``noise_std`` (its initial
    std), ``noise_decay`` (default 1.0) and ``noise_std_min`` (default 0.0) become ``action_noise``, a
    :class:`DecayingNormalActionNoise`. Other noise types are left to the Zoo (``normal``, ``ornstein-uhlenbeck``).

    :param hyperparams: an entry's hyper-parameters
    :param action_shape: the action space's shape
    :return: the hyper-parameters, with ``action_noise`` in place of those keys (a copy; the same when there are none)
    """
    if not is_decaying_normal(hyperparams):
        return hyperparams
    params = {key: value for key, value in hyperparams.items() if key not in ZOO_NOISE_KEYS}
    params["action_noise"] = DecayingNormalActionNoise(
        np.zeros(action_shape),
        np.full(action_shape, float(hyperparams["noise_std"])),
        decay=hyperparams.get("noise_decay", 1.0),
        sigma_min=hyperparams.get("noise_std_min", 0.0),
    )
    return params
