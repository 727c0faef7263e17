"""
``report``: read an experiment folder, compute Table 1's metrics, write ``table.md``, ``metrics.json``,
``curves.png`` and (for runs that log ``confidence/head_*``) ``confidence.png``. Runs that are missing, unfinished
or failed are listed in both the table and the JSON, never silently dropped.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sb3_soup.experiments import logs
from sb3_soup.experiments.grid import RunSpec
from sb3_soup.experiments.metrics import DEFAULT_WINDOW, ModelMetrics, add_speed_ups, model_metrics, paper_thresholds
from sb3_soup.experiments.plots import Curve, plot_confidence, plot_curves
from sb3_soup.experiments.runner import DONE_FILE, ERROR_FILE, SPEC_FILE, STATUS_FILE, read_json

GRID_FILE = "grid.json"
BASELINE = "ddpg"


@dataclasses.dataclass
class RunRecord:
    """
    A run of the grid and where it stands.

    :param spec: its spec
    :param status: ``"finished"``, ``"failed"``, ``"interrupted"``, ``"running"`` or ``"missing"``
    :param step: steps done
    :param error: the error of a failed run
    """

    spec: RunSpec
    status: str
    step: int = 0
    error: str | None = None


def write_grid(out: str | os.PathLike, specs: Sequence[RunSpec]) -> None:
    """
    Record the runs of an experiment folder in ``grid.json`` (merged with those already there), so that
    ``report`` knows which runs to expect.

    :param out: the experiment folder
    :param specs: the runs
    """
    path = Path(out) / GRID_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    known = {spec["run_dir"]: spec for spec in (read_json(path) or {}).get("runs", [])}
    for spec in specs:
        data = dataclasses.asdict(spec)
        data.update(checkpoint_freq=spec.checkpoint_freq, stop_after=None)
        known[spec.run_dir] = data
    path.write_text(json.dumps({"runs": list(known.values())}, indent=2, sort_keys=True))


def collect_runs(out: str | os.PathLike) -> list[RunRecord]:
    """
    :param out: the experiment folder
    :return: every run it expects (from ``grid.json``, else the ``spec.json`` files found), with its status
    """
    grid = read_json(Path(out) / GRID_FILE)
    if grid is not None:
        specs = [RunSpec(**data) for data in grid["runs"]]
    else:
        specs = [RunSpec(**json.loads(path.read_text())) for path in sorted(Path(out).glob(f"*/seed_*/{SPEC_FILE}"))]
    records = []
    for spec in specs:
        run_dir = Path(spec.run_dir)
        if not run_dir.is_dir():  # the folder was moved: look next to grid.json
            run_dir = Path(out) / spec.model / f"seed_{spec.seed}"
            spec = dataclasses.replace(spec, run_dir=str(run_dir))
        status = read_json(run_dir / STATUS_FILE) or {}
        error = read_json(run_dir / ERROR_FILE)
        if (run_dir / DONE_FILE).is_file():
            records.append(RunRecord(spec, "finished", int((read_json(run_dir / DONE_FILE) or {}).get("timesteps", 0))))
        elif error is not None:
            records.append(RunRecord(spec, "failed", int(status.get("step", 0)), str(error.get("error"))))
        elif status:
            records.append(RunRecord(spec, str(status.get("status", "running")), int(status.get("step", 0))))
        else:
            records.append(RunRecord(spec, "missing"))
    return records


def _fmt(value: float | None, digits: int = 0) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{digits}f}"


def _crossing(value: float | None, crossed: int, n_seeds: int) -> str:
    if value is None:
        return f"never (0/{n_seeds})"
    return _fmt(value) + ("" if crossed == n_seeds else f" ({crossed}/{n_seeds})")


def format_table(
    metrics: dict[str, dict[str, ModelMetrics]],
    labels: dict[str, str],
    thresholds: dict[str, tuple[float | None, float | None]],
    records: Sequence[RunRecord],
    window: int | None,
    baseline: str,
) -> str:
    """
    Table 1's layout: one row per (env, metric), one column per model.

    :param metrics: env -> model -> metrics
    :param labels: model -> column title
    :param thresholds: env -> (Episode, Speed Up) thresholds
    :param records: all runs, to list those not included
    :param window: the running-average window used
    :param baseline: the model Speed Up is measured against
    :return: Markdown
    """
    models = list(dict.fromkeys(model for env_metrics in metrics.values() for model in env_metrics))
    lines = ["| Env. | Metric | " + " | ".join(labels[model] for model in models) + " |", "|---|---|" + "---|" * len(models)]
    for env_id, env_metrics in metrics.items():
        rows: dict[str, list[str]] = {"Avg Return": [], "Max Return": [], "Episode": [], "Speed Up": [], "Seeds": []}
        for model in models:
            entry = env_metrics.get(model)
            if entry is None:
                for row in rows.values():
                    row.append("n/a")
                continue
            rows["Avg Return"].append(f"{_fmt(entry.avg_return)} ± {_fmt(entry.avg_return_std)}")
            rows["Max Return"].append(_fmt(entry.max_return))
            rows["Episode"].append(_crossing(entry.episode, entry.episode_crossed, entry.n_seeds))
            rows["Speed Up"].append(_fmt(entry.speed_up, 2))
            rows["Seeds"].append(str(entry.n_seeds))
        for index, (name, row) in enumerate(rows.items()):
            lines.append(f"| {env_id if index == 0 else ''} | {name} | " + " | ".join(row) + " |")
    lines.append("")
    running = f"last {window} episodes" if window else "all episodes so far"
    for env_id, (episode, lower) in thresholds.items():
        lines.append(
            f"- {env_id}: **Episode** = first training episode with return >= {_fmt(episode)}; **Speed Up** = "
            f"1 - E/E_{baseline}, E = first episode whose running average return ({running}) >= {_fmt(lower)}."
        )
    lines.append(
        "- Avg Return: mean ± std (ddof=0) over seeds of each seed's mean training-episode return; Max Return: best "
        "single training episode over all seeds; Episode and E: mean over the seeds that crossed, (k/n) when not all did."
    )
    excluded = [record for record in records if record.status != "finished"]
    if excluded:
        lines += ["", f"**Not included ({len(excluded)} runs):**", ""]
        for record in excluded:
            detail = f"{record.step}/{record.spec.timesteps} steps"
            if record.error:
                detail += f": {record.error}"
            lines.append(f"- `{record.spec.env_id}` `{record.spec.key}`: {record.status} ({detail})")
    return "\n".join(lines) + "\n"


def make_report(
    out: str | os.PathLike,
    thresholds: dict[str, tuple[float | None, float | None]] | None = None,
    window: int | None = DEFAULT_WINDOW,
    baseline: str = BASELINE,
    x_axis: str = "episodes",
) -> dict[str, Any]:
    """
    Compute the metrics of every finished run in ``out`` and write the report files there.

    :param out: the experiment folder
    :param thresholds: env -> (Episode, Speed Up) thresholds, overriding the paper's (Hopper, Walker2d)
    :param window: running-average window for Speed Up and the curves (``None``: cumulative mean)
    :param baseline: the model id Speed Up is measured against
    :param x_axis: x-axis of ``curves.png``: ``"episodes"`` or ``"timesteps"``
    :return: the data written to ``metrics.json``
    """
    out = Path(out)
    records = collect_runs(out)
    if not records:
        raise FileNotFoundError(f"No runs found in {out} (expected {GRID_FILE} or */seed_*/{SPEC_FILE})")
    envs = list(dict.fromkeys(record.spec.env_id for record in records))
    resolved = {env_id: (thresholds or {}).get(env_id, paper_thresholds(env_id)) for env_id in envs}
    labels = {record.spec.model: record.spec.label for record in records}
    metrics: dict[str, dict[str, ModelMetrics]] = {}
    curves: dict[str, list[Curve]] = {}
    confidence: dict[str, list[Any]] = {}
    for env_id in envs:
        metrics[env_id], curves[env_id] = {}, []
        env_records = [record for record in records if record.spec.env_id == env_id]
        for model in dict.fromkeys(record.spec.model for record in env_records):
            finished = [r for r in env_records if r.spec.model == model and r.status == "finished"]
            episodes = [logs.read_monitor(r.spec.run_dir) for r in finished]
            if not any(len(frame) for frame in episodes):
                continue
            returns = [frame["r"].to_numpy(dtype=float) for frame in episodes]
            metrics[env_id][model] = model_metrics(
                returns, *resolved[env_id], window=window, seeds=[r.spec.seed for r in finished]
            )
            curves[env_id].append(Curve(labels[model], returns, [frame["l"].to_numpy(dtype=float) for frame in episodes]))
            progress = [logs.read_progress(r.spec.run_dir) for r in finished]
            progress = [frame for frame in progress if any(col.startswith("confidence/head_") for col in frame.columns)]
            if progress and any(_is_adaptive(r.spec) for r in finished):
                confidence[f"{labels[model]}, {env_id}"] = progress
        add_speed_ups(metrics[env_id], baseline)

    files = ["table.md", "metrics.json"]
    (out / "table.md").write_text(format_table(metrics, labels, resolved, records, window, baseline))
    if any(curves.values()):
        plot_curves(
            {env_id: env_curves for env_id, env_curves in curves.items() if env_curves}, out / "curves.png", x_axis, window
        )
        files.append("curves.png")
    if confidence:
        plot_confidence(confidence, out / "confidence.png")
        files.append("confidence.png")
    data = {
        "thresholds": {env_id: {"episode": pair[0], "speed_up": pair[1]} for env_id, pair in resolved.items()},
        "window": window,
        "baseline": baseline,
        "std_ddof": 0,
        "labels": labels,
        "metrics": {
            env_id: {model: dataclasses.asdict(entry) for model, entry in env_metrics.items()}
            for env_id, env_metrics in metrics.items()
        },
        "runs": [
            {
                "env_id": r.spec.env_id,
                "model": r.spec.model,
                "seed": r.spec.seed,
                "status": r.status,
                "step": r.step,
                "timesteps": r.spec.timesteps,
                "error": r.error,
            }
            for r in records
        ],
        "not_included": [f"{r.spec.env_id}:{r.spec.key}" for r in records if r.status != "finished"],
        "files": files,
    }
    (out / "metrics.json").write_text(json.dumps(data, indent=2, default=_json_default))
    return data


def _is_adaptive(spec: RunSpec) -> bool:
    """Whether a run uses self-adaptive confidence (given explicitly, or by the ``soup`` preset)."""
    confidence = spec.hyperparams.get("confidence")
    if confidence is None and spec.hyperparams.get("preset") == "soup":
        confidence = "adaptive"
    return spec.algo == "soup" and confidence == "adaptive"


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"Not JSON serialisable: {type(value)}")
