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
    curves: dict[str, Sequence[Curve]], path: str | os.PathLike, x_axis: str = "episodes", window: int | None = DEFAULT_WINDOW
) -> None:
    """
    One panel per env: mean (line) ± std (shaded) over seeds of the running-average training return, per model.

    :param curves: env -> its models' curves
    :param path: the PNG to write
    :param x_axis: ``"episodes"`` or ``"timesteps"``
    :param window: running-average window
    """
    fig, axes = plt.subplots(1, len(curves), figsize=(6.5 * len(curves), 4.5), squeeze=False)
    for ax, (env_id, env_curves) in zip(axes[0], curves.items(), strict=True):
        for curve in env_curves:
            x, mean, std = mean_std_over_seeds(curve, x_axis, window)
            if x.size == 0:
                continue
            seeds = len([returns for returns in curve.returns if len(returns)])
            (line,) = ax.plot(x, mean, label=f"{curve.label} ({seeds} seeds)")
            ax.fill_between(x, mean - std, mean + std, color=line.get_color(), alpha=0.2)
        ax.set_title(env_id)
        ax.set_xlabel("episode" if x_axis == "episodes" else "timesteps")
        ax.set_ylabel(f"average return (last {window} episodes)" if window else "average return")
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


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
    fig.suptitle(f"Per-head confidence during training (smoothed over {smooth:.0%} of the run)", fontsize="large")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
