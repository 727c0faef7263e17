"""
Statistics of the deterministic evaluations (``evaluations.csv``) as peers publish them, computed by rliable
(Agarwal et al., 2021): per model, the interquartile mean (IQM) of the runs' evaluation returns at a step with its 95%
stratified-bootstrap confidence interval, and the probability of improvement over a baseline with its interval.

A run's score at a step is the mean return of its evaluation episodes at that step (SB3's ``EvalCallback``'s
``mean_reward``). ``report`` does not normalise scores: each env is reported on its own. The screening suite's report
(:mod:`sb3_soup.experiments.screen`) aggregates normalised scores over tasks: the functions below take a ``(runs,)``
array (one task) or a ``(runs, tasks)`` matrix, with rliable's stratified bootstrap (runs resampled within each task).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

# Bootstrap resamples: rliable's examples use 50,000; 10,000 give intervals stable to about 1% in a few seconds.
DEFAULT_REPS = 10_000
CONFIDENCE = 0.95


@dataclasses.dataclass
class Estimate:
    """A point estimate with its 95% stratified-bootstrap confidence interval."""

    value: float
    low: float
    high: float

    def format(self, digits: int = 0) -> str:
        """:return: ``value [low, high]``"""
        return f"{self.value:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"


def _rliable():  # type: ignore[no-untyped-def]
    """rliable's ``library`` and ``metrics``, or a clear error when the ``experiments`` extra is not installed."""
    try:
        from rliable import library, metrics
    except ImportError as error:
        raise ImportError(f"the evaluation statistics need rliable ({error}): pip install 'sb3-soup[experiments]'") from error
    return library, metrics


def _matrix(scores: np.ndarray) -> np.ndarray:
    """``(runs,)`` or ``(runs, tasks)`` scores as rliable's ``(runs, tasks)`` matrix."""
    matrix = np.asarray(scores, dtype=float)
    return matrix.reshape(-1, 1) if matrix.ndim == 1 else matrix


def run_scores(evaluations: Sequence[tuple[np.ndarray, np.ndarray]], step: int, last: int = 1) -> np.ndarray:
    """
    :param evaluations: per run, its ``(steps, mean returns)`` arrays, in the order of the steps
    :param step: the evaluation step
    :param last: how many evaluations a run's score averages: its last ``last`` up to ``step`` (1: the one at ``step``;
        e.g. 6 at 200k steps with an evaluation every 10k: 150k-200k, less noisy than one evaluation)
    :return: ``(n_runs,)`` the runs' mean evaluation return at ``step`` (averaged over the ``last`` evaluations)
    :raises ValueError: when a run was not evaluated at ``step``, or fewer than ``last`` times up to it
    """
    if isinstance(last, bool) or not isinstance(last, (int, np.integer)) or last < 1:
        raise ValueError(f"the number of evaluations a run's score averages must be a whole number >= 1, got {last!r}")
    scores = []
    for steps, returns in evaluations:
        steps = np.asarray(steps)
        if not (steps == step).any():
            raise ValueError(f"a run has no evaluation at step {step} (its steps: {steps.tolist()})")
        up_to = np.flatnonzero(steps <= step)
        if up_to.size < last:
            raise ValueError(f"a run has {up_to.size} evaluations up to step {step}, fewer than the {last} its score averages")
        scores.append(float(np.mean(np.asarray(returns)[up_to[-last:]])))
    return np.asarray(scores)


def iqm(scores: np.ndarray, reps: int = DEFAULT_REPS, seed: int = 0) -> Estimate:
    """
    :param scores: ``(n_runs,)``, or ``(n_runs, n_tasks)``: the IQM of all its scores
    :param reps: bootstrap resamples
    :param seed: the bootstrap's seed (reports are reproducible)
    :return: the interquartile mean with its 95% stratified-bootstrap interval
    """
    return aggregates(scores, ("iqm",), reps=reps, seed=seed)["iqm"]


AGGREGATES = ("iqm", "mean", "median")


def aggregates(
    scores: np.ndarray, names: Sequence[str] = AGGREGATES, reps: int = DEFAULT_REPS, seed: int = 0
) -> dict[str, Estimate]:
    """
    :param scores: ``(n_runs,)`` or ``(n_runs, n_tasks)``
    :param names: which of :data:`AGGREGATES` (rliable's ``aggregate_iqm``, ``aggregate_mean``, ``aggregate_median``)
    :param reps: bootstrap resamples (one bootstrap for all of them)
    :param seed: the bootstrap's seed
    :return: name -> the statistic with its 95% stratified-bootstrap interval
    """
    rly, metrics = _rliable()
    functions = [getattr(metrics, f"aggregate_{name}") for name in names]
    np.random.seed(seed)  # rliable's bootstrap draws from NumPy's global generator
    points, intervals = rly.get_interval_estimates(
        {"x": _matrix(scores)},
        lambda matrix: np.array([function(matrix) for function in functions]),
        reps=reps,
        confidence_interval_size=CONFIDENCE,
    )
    return {
        name: Estimate(float(points["x"][index]), float(intervals["x"][0, index]), float(intervals["x"][1, index]))
        for index, name in enumerate(names)
    }


def probability_of_improvement(scores: np.ndarray, baseline: np.ndarray, reps: int = DEFAULT_REPS, seed: int = 0) -> Estimate:
    """
    :param scores: ``(n_runs,)`` of the model, or ``(n_runs, n_tasks)``
    :param baseline: ``(m_runs,)`` of the baseline, or ``(m_runs, n_tasks)`` (the same tasks)
    :param reps: bootstrap resamples
    :param seed: the bootstrap's seed
    :return: P(a run of the model scores higher than a run of the baseline on a task), ties counting half, averaged
        over the tasks, with its 95% stratified-bootstrap interval
    """
    rly, metrics = _rliable()
    np.random.seed(seed)
    pair = (_matrix(scores), _matrix(baseline))
    points, intervals = rly.get_interval_estimates(
        {"x,y": pair}, metrics.probability_of_improvement, reps=reps, confidence_interval_size=CONFIDENCE
    )
    low, high = np.asarray(intervals["x,y"], dtype=float).ravel()
    return Estimate(float(points["x,y"]), float(low), float(high))


def iqm_curve(
    evaluations: Sequence[tuple[np.ndarray, np.ndarray]], steps: Sequence[int], reps: int = 2_000, seed: int = 0
) -> list[Estimate]:
    """
    :param evaluations: per run, its ``(steps, mean returns)``
    :param steps: the evaluation steps every run has
    :param reps: bootstrap resamples per step
    :param seed: the bootstrap's seed
    :return: the IQM with its interval at each step
    """
    return [iqm(run_scores(evaluations, step), reps=reps, seed=seed) for step in steps]


def performance_profiles(
    scores: dict[str, np.ndarray], taus: np.ndarray, reps: int = 2_000, seed: int = 0
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """
    rliable's score distributions (performance profiles): per model, the fraction of its runs scoring above each tau.

    :param scores: model -> ``(n_runs, n_tasks)``
    :param taus: the thresholds
    :param reps: bootstrap resamples of the bands
    :param seed: the bootstrap's seed
    :return: model -> ``(len(taus),)`` fractions, and model -> ``(2, len(taus))`` their 95% stratified-bootstrap band
    """
    rly, _ = _rliable()
    np.random.seed(seed)
    return rly.create_performance_profile(
        {model: _matrix(matrix) for model, matrix in scores.items()}, taus, reps=reps, confidence_interval_size=CONFIDENCE
    )


def common_steps(evaluations: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[int]:
    """:return: the evaluation steps that every run has, in order"""
    if not evaluations:
        return []
    common = set(np.asarray(evaluations[0][0]).tolist())
    for steps, _ in evaluations[1:]:
        common &= set(np.asarray(steps).tolist())
    return sorted(int(step) for step in common)


def read_run(run_dir: str) -> tuple[np.ndarray, np.ndarray]:
    """
    :param run_dir: a run's folder
    :return: its evaluation steps and the mean return of the episodes of each (empty arrays when it has none)
    """
    from sb3_soup.experiments import logs

    frame = logs.read_evaluations(run_dir)
    if not len(frame):
        return np.zeros(0, dtype=int), np.zeros(0)
    means = frame.groupby("step")["return"].mean()
    return means.index.to_numpy(dtype=int), means.to_numpy(dtype=float)
