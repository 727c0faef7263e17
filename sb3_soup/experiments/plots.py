"""Figures 4, 5 and 7 (learning curves, mean ± std over seeds) and Figure 6 (per-head confidence over training)."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.ticker import MaxNLocator

from sb3_soup.experiments.metrics import DEFAULT_WINDOW, running_average


@dataclass
class Curve:
    """
    One model's runs in one env.

    :param label: legend entry
    :param returns: per seed, its episode returns
    :param lengths: per seed, its episode lengths (for a timestep x-axis)
    """

    label: str
    returns: list[np.ndarray]
    lengths: list[np.ndarray]


def mean_std_over_seeds(
    curve: Curve, x_axis: str = "episodes", window: int | None = DEFAULT_WINDOW, points: int = 200
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    The running-average return of each seed, aligned on a common x-axis, then mean and std over seeds.

    :param curve: the model's runs
    :param x_axis: ``"episodes"`` (up to the shortest seed's episode count) or ``"timesteps"`` (interpolated at
        ``points`` steps up to the shortest seed's last finished episode)
    :param window: running-average window (see :func:`~sb3_soup.experiments.metrics.running_average`)
    :param points: grid size for the timestep axis
    :return: x, mean, std
    """
    smoothed = [running_average(returns, window) for returns in curve.returns if len(returns)]
    if not smoothed:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    if x_axis == "episodes":
        n = min(len(values) for values in smoothed)
        stack = np.stack([values[:n] for values in smoothed])
        x = np.arange(1, n + 1)
    else:
        ends = [np.cumsum(lengths) for lengths in curve.lengths if len(lengths)]
        x = np.linspace(max(end[0] for end in ends), min(end[-1] for end in ends), points)
        stack = np.stack([np.interp(x, end, values) for end, values in zip(ends, smoothed, strict=True)])
    return x, stack.mean(axis=0), stack.std(axis=0)


def plot_curves(
    curves: dict[str, Sequence[Curve]],
    path: str | os.PathLike,
    x_axis: str = "both",
    window: int | None = DEFAULT_WINDOW,
    thresholds: Mapping[str, tuple[float | None, float | None]] | None = None,
) -> None:
    """
    Figures 4, 5 and 7: per env, the mean (line) ± std (shaded) over seeds of each model's running-average training
    return, against the episode (the paper's axis) and/or the timestep (what the runs' budget is counted in).

    :param curves: env -> its models' curves
    :param path: the PNG to write
    :param x_axis: ``"episodes"``, ``"timesteps"`` or ``"both"`` (two panels per env)
    :param window: running-average window
    :param thresholds: env -> (Episode, Speed Up) thresholds, drawn as dashed lines when they fall in the plotted range
    """
    kinds = ["episodes", "timesteps"] if x_axis == "both" else [x_axis]
    fig, axes = plt.subplots(len(curves), len(kinds), figsize=(6.4 * len(kinds), 4.6 * len(curves)), squeeze=False)
    labels = list(dict.fromkeys(curve.label for env_curves in curves.values() for curve in env_curves))
    colours = {label: f"C{index % 10}" for index, label in enumerate(labels)}
    for row, (env_id, env_curves) in enumerate(curves.items()):
        for col, kind in enumerate(kinds):
            ax = axes[row][col]
            for curve in env_curves:
                x, mean, std = mean_std_over_seeds(curve, kind, window)
                if x.size == 0:
                    continue
                seeds = len([returns for returns in curve.returns if len(returns)])
                colour = colours[curve.label]
                ax.plot(x, mean, color=colour, lw=1.6, label=f"{curve.label}, {seeds} seed{'s' if seeds > 1 else ''}")
                ax.fill_between(x, mean - std, mean + std, color=colour, alpha=0.18, lw=0)
            _threshold_lines(ax, (thresholds or {}).get(env_id, (None, None)))
            ax.set_title(f"{env_id}: return against {'episode' if kind == 'episodes' else 'timestep'}")
            ax.set_xlabel("training episode" if kind == "episodes" else "timestep")
            ax.set_ylabel(
                f"return, running mean of last {window} episodes" if window else "return, mean of all episodes so far"
            )
            ax.grid(alpha=0.3)
            ax.legend(fontsize="small", loc="best")
            if kind == "timesteps":
                ax.ticklabel_format(axis="x", style="sci", scilimits=(3, 3))
            else:
                ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    fig.suptitle("Learning curves: mean ± std over seeds (shaded)", fontsize="large")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _threshold_lines(ax: plt.Axes, thresholds: tuple[float | None, float | None]) -> None:
    """Dashed lines at the Episode and Speed Up thresholds that fall within the data's range (not to squash it)."""
    low, high = ax.get_ylim()
    for value, name in zip(thresholds, ("Episode threshold", "Speed Up threshold"), strict=True):
        if value is not None and low <= value <= high:
            ax.axhline(value, color="0.4", ls="--", lw=0.9)
            ax.annotate(f"{name} {value:g}", (0.99, value), xycoords=("axes fraction", "data"), ha="right", va="bottom",
                        fontsize="x-small", color="0.3")  # fmt: skip


def plot_confidence(
    panels: Mapping[str, Sequence[tuple[int, pd.DataFrame]]], path: str | os.PathLike, smooth: float = 0.05
) -> None:
    """
    Figure 6: each critic head's confidence over training, one panel per (adaptive model, seed). Heads are not
    averaged over seeds: head i of one seed has nothing to do with head i of another.

    :param panels: title -> per seed, ``(seed, frame)`` with ``time/total_timesteps`` and ``confidence/head_{i}``
        columns (the run's ``progress.csv``)
    :param path: the PNG to write
    :param smooth: rolling-mean window as a fraction of the run's log rows (the paper's Figure 6 is smoothed too);
        the raw values are drawn faintly behind
    """
    n_rows = len(panels)
    n_cols = max(len(seeds) for seeds in panels.values())
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(4.8 * n_cols, 3.6 * n_rows), squeeze=False, sharey=True)
    for row, (title, seeds) in enumerate(panels.items()):
        for col in range(n_cols):
            ax = axes[row][col]
            if col >= len(seeds):
                ax.axis("off")
                continue
            seed, frame = seeds[col]
            heads = sorted(
                (name for name in frame.columns if name.startswith("confidence/head_")),
                key=lambda name: int(name.rsplit("_", 1)[1]),
            )
            window = max(1, int(len(frame) * smooth))
            for head in heads:
                data = frame[["time/total_timesteps", head]].dropna()
                x = data["time/total_timesteps"].to_numpy()
                (line,) = ax.plot(x, data[head].rolling(window, min_periods=1).mean(), label=head.split("_")[-1], lw=1.5)
                ax.plot(x, data[head], color=line.get_color(), alpha=0.15, lw=0.6)
            ax.set_title(f"{title}\nseed {seed}", fontsize="medium")
            ax.set_xlabel("timesteps")
            if col == 0:
                ax.set_ylabel("confidence c_i (mean per episode)")
            ax.grid(alpha=0.3)
            ax.legend(title="head", fontsize="small", ncol=2 if len(heads) > 5 else 1)
    # on two lines for a single panel, which is too narrow for it
    title = "Per-head confidence during training" + ("\n" if n_cols < 2 else " ") + f"(smoothed over {smooth:.0%} of the run)"
    fig.suptitle(title, fontsize="large")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_evaluations(
    curves: Mapping[str, Sequence[tuple[str, Sequence[int], Sequence[tuple[float, float, float]]]]],
    path: str | os.PathLike,
    columns: int | None = None,
    references: Mapping[str, float] | None = None,
) -> None:
    """
    Deterministic evaluation return over training: the IQM over runs with its 95% confidence band, one panel per env.

    :param curves: env -> [(label, steps, [(iqm, low, high) per step])]
    :param path: the PNG file
    :param columns: panels per row (default: every env in one row)
    :param references: env -> a return drawn as a dotted line (e.g. a random policy's), labelled "random policy"
    """
    columns = min(columns or len(curves), len(curves))
    rows = -(-len(curves) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(6 * columns, 4.2 * rows), squeeze=False)
    for ax, (env_id, env_curves) in zip(axes.ravel(), curves.items()):
        for label, steps, estimates in env_curves:
            values = np.asarray(estimates, dtype=float).reshape(-1, 3)
            ax.plot(steps, values[:, 0], label=label)
            ax.fill_between(steps, values[:, 1], values[:, 2], alpha=0.2)
        if references is not None and env_id in references:
            ax.axhline(references[env_id], color="0.5", ls=":", lw=1, label="random policy")
        ax.set_title(f"{env_id}: evaluation return (IQM, 95% CI)")
        ax.set_xlabel("environment steps")
        ax.set_ylabel("return")
        ax.legend(fontsize="small")
    for ax in axes.ravel()[len(curves) :]:
        ax.set_visible(False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
