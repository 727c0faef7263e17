"""
The paper's Table 1 metrics (soup-spec.md, "Paper metrics (Table 1)"), computed from training-episode returns.

Per run (one seed), from its returns ``R_1..R_n`` in episode order:

- **Avg Return**: ``mean(R)``; a model's entry is the mean ± std (population std, ``ddof=0``) of that over its seeds.
- **Max Return**: ``max(R)``; a model's entry is the maximum over all its seeds' episodes.
- **Episode**: the first episode ``e`` (1-based) with ``R_e >= threshold`` (Hopper 2000, Walker2d 3000).
- **E** (for Speed Up): the first episode ``e`` at which the running average return crosses the lower threshold
  (Hopper 1000, Walker2d 1500). The running average at ``e`` is the mean of the last ``window`` returns
  ``R_{max(1, e-window+1)}..R_e`` (``window=100``, SB3's ``rollout/ep_rew_mean``); ``window=None`` gives the
  cumulative mean ``mean(R_1..R_e)``.

A model's Episode and E are the mean over the seeds that crossed (the number of seeds that crossed is reported
alongside; seeds that never crossed are not counted as crossing at the end). **Speed Up** is
``1 - E_model / E_DDPG`` with those seed means; undefined when either never crossed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

# env name (the id without its version) -> (Episode threshold, Speed Up threshold), from Table 1's caption.
PAPER_THRESHOLDS: dict[str, tuple[float, float]] = {"Hopper": (2000.0, 1000.0), "Walker2d": (3000.0, 1500.0)}
DEFAULT_WINDOW = 100


def paper_thresholds(env_id: str) -> tuple[float | None, float | None]:
    """
    :param env_id: e.g. ``"Hopper-v4"``
    :return: the paper's (Episode, Speed Up) thresholds for the env, ``(None, None)`` when it has none
    """
    return PAPER_THRESHOLDS.get(env_id.split("-v")[0], (None, None))


def running_average(returns: ArrayLike, window: int | None = DEFAULT_WINDOW) -> np.ndarray:
    """
    :param returns: episode returns in order
    :param window: trailing window length, ``None`` for the cumulative mean
    :return: the running average after each episode
    """
    values = np.asarray(returns, dtype=float)
    sums = np.cumsum(values)
    counts = np.arange(1, len(values) + 1)
    if window is None or window >= len(values):
        return sums / counts
    shifted = np.concatenate([np.zeros(window), sums[:-window]])
    return (sums - shifted) / np.minimum(counts, window)


def first_crossing(values: ArrayLike, threshold: float | None) -> int | None:
    """
    :param values: a curve over episodes
    :param threshold: the threshold
    :return: the first episode (1-based) whose value is ``>= threshold``; ``None`` if none (or no threshold)
    """
    if threshold is None:
        return None
    hits = np.flatnonzero(np.asarray(values, dtype=float) >= threshold)
    return int(hits[0]) + 1 if hits.size else None


def speed_up(episode_model: float | None, episode_baseline: float | None) -> float | None:
    """
    :param episode_model: the model's E
    :param episode_baseline: DDPG's E
    :return: ``1 - E_model / E_DDPG``, ``None`` when either is undefined
    """
    if episode_model is None or episode_baseline is None or episode_baseline == 0:
        return None
    return 1.0 - episode_model / episode_baseline


def _mean_or_none(values: Sequence[Any]) -> float | None:
    crossed = [value for value in values if value is not None]
    return float(np.mean(crossed)) if crossed else None


@dataclasses.dataclass
class ModelMetrics:
    """
    One model's column of Table 1.

    :param n_seeds: the seeds it was computed from
    :param avg_return: mean over seeds of the per-seed mean return
    :param avg_return_std: std over seeds of the per-seed mean return
    :param max_return: highest single episode return
    :param episode: mean over crossing seeds of the first episode reaching the threshold
    :param episode_crossed: how many seeds crossed it
    :param speedup_episode: mean over crossing seeds of E (running average crossing the lower threshold)
    :param speedup_crossed: how many seeds' running averages crossed
    :param speed_up: ``1 - E / E_DDPG`` (set by :func:`add_speed_ups`)
    :param per_seed: the per-seed values
    """

    n_seeds: int
    avg_return: float
    avg_return_std: float
    max_return: float
    episode: float | None
    episode_crossed: int
    speedup_episode: float | None
    speedup_crossed: int
    speed_up: float | None = None
    per_seed: list[dict[str, Any]] = dataclasses.field(default_factory=list)


def model_metrics(
    runs: Sequence[ArrayLike],
    threshold: float | None,
    speedup_threshold: float | None,
    window: int | None = DEFAULT_WINDOW,
    seeds: Sequence[int] | None = None,
) -> ModelMetrics:
    """
    :param runs: per seed, its training-episode returns in order (seeds without episodes are skipped)
    :param threshold: the Episode threshold
    :param speedup_threshold: the Speed Up (running average) threshold
    :param window: see :func:`running_average`
    :param seeds: the seeds' numbers, for ``per_seed``
    :return: the model's metrics (without Speed Up; see :func:`add_speed_ups`)
    """
    seeds = list(seeds) if seeds is not None else list(range(len(runs)))
    per_seed: list[dict[str, Any]] = []
    for seed, returns in zip(seeds, runs, strict=False):
        values = np.asarray(returns, dtype=float)
        if values.size == 0:
            continue
        per_seed.append(
            {
                "seed": seed,
                "episodes": int(values.size),
                "avg_return": float(values.mean()),
                "max_return": float(values.max()),
                "episode": first_crossing(values, threshold),
                "speedup_episode": first_crossing(running_average(values, window), speedup_threshold),
            }
        )
    if not per_seed:
        raise ValueError("No episodes to compute metrics from")
    means = np.array([entry["avg_return"] for entry in per_seed])
    return ModelMetrics(
        n_seeds=len(per_seed),
        avg_return=float(means.mean()),
        avg_return_std=float(means.std(ddof=0)),
        max_return=float(max(entry["max_return"] for entry in per_seed)),
        episode=_mean_or_none([entry["episode"] for entry in per_seed]),
        episode_crossed=sum(entry["episode"] is not None for entry in per_seed),
        speedup_episode=_mean_or_none([entry["speedup_episode"] for entry in per_seed]),
        speedup_crossed=sum(entry["speedup_episode"] is not None for entry in per_seed),
        per_seed=per_seed,
    )


def add_speed_ups(metrics: dict[str, ModelMetrics], baseline: str) -> None:
    """
    Fill in every model's Speed Up against ``baseline`` (left ``None`` for the baseline itself or when it is absent).

    :param metrics: model -> metrics
    :param baseline: the model id of DDPG
    """
    reference = metrics.get(baseline)
    for model, entry in metrics.items():
        if reference is not None and model != baseline:
            entry.speed_up = speed_up(entry.speedup_episode, reference.speedup_episode)
