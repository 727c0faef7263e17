"""
``trap``: how long each run of an experiment folder spent in a degenerate policy that ends every episode the same
short way (on Hopper: every joint torque at its bound, a fall after 21-24 steps, return about 39), and how saturated
its final deterministic actions are.

A run is *trapped* in a window of ``window`` steps after its random warm-up (``learning_starts``) when more than
``fraction`` of the training episodes that end in the window have a length in ``lengths``. Episodes come from the
run's Monitor CSV; an episode belongs to the window in which it ends, and a window in which no episode ends is not
trapped. The *saturation* of a run is the fraction of action components of its final model (``model.zip``), acting
deterministically for a few evaluation episodes, whose magnitude in the policy's [-1, 1] scale exceeds ``bound``.
Where the run ended up is the mean return of the training episodes that end in the last part of its steps.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sb3_soup.experiments import logs
from sb3_soup.experiments.report import RunRecord, collect_runs, recorded_heads, report_target, select_columns
from sb3_soup.experiments.runner import FINAL_MODEL, algo_class

HOPPER_FALL_LENGTHS = (21, 24)


@dataclasses.dataclass
class TrapResult:
    """
    One run's trap measurement.

    :param model: the run's model id
    :param label: its column title
    :param seed: its seed
    :param learning_steps: steps after the warm-up that windows cover (whole windows only)
    :param steps_trapped: steps of the trapped windows
    :param last_trapped_step: the last step of the last trapped window (``None``: never trapped)
    :param trap_return: mean return of the trap-length episodes after the warm-up (``None``: none)
    :param final_return: mean return of the episodes that end in the last ``final_fraction`` of the run's steps
    :param saturation: fraction of saturated final deterministic action components (``None``: not measured)
    """

    model: str
    label: str
    seed: int
    learning_steps: int
    steps_trapped: int
    last_trapped_step: int | None
    trap_return: float | None
    final_return: float | None = None
    saturation: float | None = None


def _is_trap(lengths: np.ndarray, trap_lengths: tuple[int, int]) -> np.ndarray:
    """:return: which episodes have a trap length (both bounds included)"""
    return (lengths >= trap_lengths[0]) & (lengths <= trap_lengths[1])


def trapped_windows(
    lengths: Sequence[int] | np.ndarray,
    start: int,
    end: int,
    window: int = 1000,
    trap_lengths: tuple[int, int] = HOPPER_FALL_LENGTHS,
    fraction: float = 0.9,
) -> np.ndarray:
    """
    :param lengths: the run's episode lengths, in order (its first episode starts at step 0)
    :param start: first step covered (the warm-up's end, ``learning_starts``)
    :param end: the run's last step
    :param window: window size in steps
    :param trap_lengths: (shortest, longest) episode length that counts as the trap's episode, both included
    :param fraction: a window is trapped when more than this fraction of the episodes that end in it are trap episodes
    :return: one bool per whole window ``(start + j * window, start + (j + 1) * window]``
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    ends = np.cumsum(lengths)  # step at which each episode ends
    n_windows = max(0, (end - start) // window)
    inside = (ends > start) & (ends <= start + n_windows * window)
    index = (ends[inside] - start - 1) // window  # (E,) window of each episode
    is_trap = _is_trap(lengths[inside], trap_lengths)
    episodes = np.bincount(index, minlength=n_windows)  # (W,)
    traps = np.bincount(index, weights=is_trap, minlength=n_windows)  # (W,)
    return (episodes > 0) & (traps > fraction * np.maximum(episodes, 1))


def action_saturation(model: Any, env_id: str, episodes: int = 3, seed: int = 0, bound: float = 0.99) -> float:
    """
    :param model: a trained SB3 model
    :param env_id: the Gymnasium env to act in
    :param episodes: evaluation episodes (deterministic actions), reset with seeds ``seed, seed + 1, ...``
    :param bound: a component counts as saturated when its magnitude in [-1, 1] scale exceeds this
    :return: the fraction of saturated action components over every step of the episodes
    """
    import gymnasium as gym

    env = gym.make(env_id)
    saturated = total = 0
    try:
        for episode in range(episodes):
            obs, _ = env.reset(seed=seed + episode)
            done = False
            while not done:
                action, _ = model.predict(obs, deterministic=True)
                scaled = model.policy.scale_action(np.asarray(action))
                saturated += int(np.sum(np.abs(scaled) > bound))
                total += int(np.size(scaled))
                obs, _, terminated, truncated, _ = env.step(action)
                done = terminated or truncated
    finally:
        env.close()
    return saturated / max(total, 1)


def _default_learning_starts(algo: str) -> int:
    """:return: the warm-up of a run whose hyper-parameters do not give it: its algorithm's default"""
    return int(inspect.signature(algo_class(algo)).parameters["learning_starts"].default)


def measure_run(
    record: RunRecord,
    label: str,
    window: int = 1000,
    trap_lengths: tuple[int, int] = HOPPER_FALL_LENGTHS,
    fraction: float = 0.9,
    eval_episodes: int = 3,
    final_fraction: float = 0.2,
) -> TrapResult:
    """
    :param record: a finished run
    :param label: its column title
    :param window: see :func:`trapped_windows`
    :param trap_lengths: see :func:`trapped_windows`
    :param fraction: see :func:`trapped_windows`
    :param eval_episodes: episodes for :func:`action_saturation` (0: not measured)
    :param final_fraction: the part of the run, at its end, whose episodes give ``final_return``
    :return: the run's measurement
    """
    spec = record.spec
    monitor = logs.read_monitor(spec.run_dir)
    lengths = monitor["l"].to_numpy(dtype=np.int64)
    start = int(spec.hyperparams.get("learning_starts", _default_learning_starts(spec.algo)))
    trapped = trapped_windows(lengths, start, record.step, window, trap_lengths, fraction)
    ends = np.cumsum(lengths)  # step at which each episode ends
    trap_after_warm_up = (ends > start) & _is_trap(lengths, trap_lengths)
    returns = monitor["r"].to_numpy(dtype=float)
    final = returns[ends > record.step * (1.0 - final_fraction)]
    last = int(start + (np.flatnonzero(trapped)[-1] + 1) * window) if trapped.any() else None
    saturation = None
    if eval_episodes > 0:
        model = algo_class(spec.algo).load(Path(spec.run_dir) / FINAL_MODEL, device="cpu")
        saturation = action_saturation(model, spec.env_id, eval_episodes, seed=spec.seed)
    return TrapResult(
        spec.model,
        label,
        spec.seed,
        learning_steps=len(trapped) * window,
        steps_trapped=int(trapped.sum()) * window,
        last_trapped_step=last,
        trap_return=float(returns[trap_after_warm_up].mean()) if trap_after_warm_up.any() else None,
        final_return=float(final.mean()) if final.size else None,
        saturation=saturation,
    )


def format_trap_table(results: Sequence[TrapResult], window: int, final_fraction: float = 0.2) -> str:
    """:return: a markdown table, one row per model, seeds separated by ``/``"""
    by_model: dict[str, list[TrapResult]] = {}
    for result in results:
        by_model.setdefault(result.label, []).append(result)
    lines = [
        f"| model | seeds | steps trapped | last trapped step | final actions saturated | return, last {final_fraction:.0%} |",
        "|---|---|---|---|---|---|",
    ]

    def steps(value: int | None) -> str:
        return "-" if value is None else f"{value / 1000:g}k"

    for label, rows in by_model.items():
        rows = sorted(rows, key=lambda row: row.seed)
        total = rows[0].learning_steps
        cells = [
            " / ".join(str(row.seed) for row in rows),
            " / ".join(steps(row.steps_trapped) for row in rows) + f" (of {steps(total)})",
            " / ".join(steps(row.last_trapped_step) for row in rows),
            " / ".join("-" if row.saturation is None else f"{row.saturation:.0%}" for row in rows),
            " / ".join("-" if row.final_return is None else f"{row.final_return:.0f}" for row in rows),
        ]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + (
        f"\n\n{window}-step windows after each run's warm-up; the last column is the mean return of the training "
        f"episodes that end in the last {final_fraction:.0%} of each run's steps.\n"
    )


def trap_report(
    out: str | os.PathLike,
    suite: str | None = None,
    window: int = 1000,
    trap_lengths: tuple[int, int] = HOPPER_FALL_LENGTHS,
    fraction: float = 0.9,
    eval_episodes: int = 3,
    report_dir: str | os.PathLike | None = None,
    final_fraction: float = 0.2,
) -> tuple[str, list[TrapResult], list[str]]:
    """
    Measure every finished run of a folder (or of one suite of it) and write ``trap.md`` and ``trap.json``.

    :param out: the experiment folder
    :param suite: only this suite's models, with its column titles (written to ``out/report-<suite>``)
    :param report_dir: where to write (default: ``out``, or ``out/report-<suite>`` with a suite)
    :param final_fraction: see :func:`measure_run`
    :return: the table, the measurements, and the runs left out because they are not finished
    """
    out = Path(out)
    if window <= 0:
        raise ValueError(f"window must be a positive number of steps, got {window}")
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"fraction must be in [0, 1), got {fraction}")
    if not 0.0 < final_fraction <= 1.0:
        raise ValueError(f"final_fraction must be in (0, 1], got {final_fraction}")
    if trap_lengths[0] > trap_lengths[1] or trap_lengths[0] < 1:
        raise ValueError(f"lengths must be 'SHORTEST-LONGEST' with 1 <= SHORTEST <= LONGEST, got {trap_lengths}")
    records = collect_runs(out)
    columns = select_columns(records, suite, recorded_heads(out))
    if not columns:
        raise ValueError(f"No runs{f' of the {suite!r} suite' if suite else ''} in {out}")
    results, skipped = [], []
    for column in columns:
        for record in sorted(column.records, key=lambda record: record.spec.seed):
            if record.status != "finished":
                skipped.append(f"{record.spec.key} ({record.status})")
                continue
            results.append(measure_run(record, column.label, window, trap_lengths, fraction, eval_episodes, final_fraction))
    table = format_trap_table(results, window, final_fraction)
    if skipped:
        table += "\nNot finished, left out: " + ", ".join(skipped) + "\n"
    target = report_target(out, suite, report_dir)
    (target / "trap.md").write_text(table)
    settings = {
        "window": window,
        "lengths": list(trap_lengths),
        "fraction": fraction,
        "eval_episodes": eval_episodes,
        "final_fraction": final_fraction,
    }
    data = {"settings": settings, "runs": [dataclasses.asdict(result) for result in results], "not_finished": skipped}
    (target / "trap.json").write_text(json.dumps(data, indent=2))
    return table, results, skipped
