"""
``report``: read an experiment folder, compute Table 1's metrics, write ``table.md``, ``metrics.json``,
``curves.png`` and (for runs with self-adaptive confidence) ``confidence.png``; from the runs' deterministic
evaluations, the statistics peers publish (rliable's IQM, 95% intervals, probability of improvement) in
``evaluation.md`` and ``evaluation.png`` (see :mod:`sb3_soup.experiments.evaluation`).

A folder may hold several suites' runs (they share the runs they have in common, see
:attr:`~sb3_soup.experiments.grid.Variant.same_as`): ``suite`` narrows the report to one suite's columns, with that
suite's titles and Speed Up baseline, written to ``report-<suite>/``.

Runs that are missing, unfinished or failed are listed in both the table and the JSON, never silently dropped. By
default the metrics use finished runs only; ``partial=True`` also uses the episodes that unfinished runs have logged
so far, and marks every number that depends on them.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sb3_soup.experiments import evaluation, logs
from sb3_soup.experiments.grid import SUITES, RunSpec, suite_columns
from sb3_soup.experiments.metrics import DEFAULT_WINDOW, ModelMetrics, add_speed_ups, model_metrics, paper_thresholds
from sb3_soup.experiments.plots import Curve, plot_confidence, plot_curves, plot_evaluations
from sb3_soup.experiments.runner import (
    DONE_FILE,
    ERROR_FILE,
    LOCKING,
    SPEC_FILE,
    STATUS_FILE,
    busy_reason,
    read_json,
    write_json,
)

GRID_FILE = "grid.json"
BASELINE = "ddpg"
PARTIAL_MARK = "†"


@dataclasses.dataclass
class RunRecord:
    """
    A run of the grid and where it stands.

    :param spec: its spec (``run_dir`` is its folder in the experiment folder being reported)
    :param status: ``"finished"``, ``"failed"``, ``"interrupted"``, ``"running"``, ``"stalled"`` (its status says
        running, but no process holds its lock: the process training it died) or ``"missing"`` (not started)
    :param step: steps done
    :param error: the error of a failed run
    """

    spec: RunSpec
    status: str
    step: int = 0
    error: str | None = None


@dataclasses.dataclass
class Column:
    """
    One model's column of the table.

    :param model: the model id (its folder name, e.g. ``dbddpg-k5``)
    :param label: the column title
    :param records: its runs (one per seed)
    :param variant: the suite's variant it stands for (e.g. ``none`` for ``dbddpg-k5`` in the confidence suite)
    """

    model: str
    label: str
    records: list[RunRecord]
    variant: str | None = None


def _run_key(data: dict[str, Any]) -> str:
    return f"{data['model']}/seed_{data['seed']}"


def write_grid(
    out: str | os.PathLike, specs: Sequence[RunSpec], suite: str | None = None, heads: Sequence[int] | None = None
) -> None:
    """
    Record the runs of an experiment folder in ``grid.json`` (merged with those already there, one entry per
    ``model/seed``), so that ``report`` knows which runs to expect, and the head counts a suite was run with.

    :param out: the experiment folder
    :param specs: the runs
    :param suite: the suite they were run for
    :param heads: the head counts asked for (``--heads``), recorded for ``suite``
    """
    path = Path(out) / GRID_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    grid = read_json(path) or {}
    known = {_run_key(data): data for data in grid.get("runs", [])}
    for spec in specs:
        data = dataclasses.asdict(spec)
        data.update(stop_after=None)
        known[spec.key] = data
    suites = dict(grid.get("suites", {}))
    if suite is not None:
        recorded = set(suites.get(suite, {}).get("heads", [])) | set(heads or SUITES[suite].heads)
        suites[suite] = {"heads": sorted(recorded)}
    write_json(path, {"runs": list(known.values()), "suites": suites})


def _run_status(run_dir: Path) -> tuple[str, int, str | None]:
    """A run folder's status, steps done and error."""
    status = read_json(run_dir / STATUS_FILE) or {}
    error = read_json(run_dir / ERROR_FILE)
    step = int(status.get("step", 0))
    if (run_dir / DONE_FILE).is_file():
        return "finished", int((read_json(run_dir / DONE_FILE) or {}).get("timesteps", step)), None
    if error is not None:
        return "failed", step, str(error.get("error"))
    if not status:
        return "missing", 0, None
    state = str(status.get("status", "running"))
    if state == "running" and LOCKING and busy_reason(run_dir) is None:
        state = "stalled"
    return state, step, None


def collect_runs(out: str | os.PathLike) -> list[RunRecord]:
    """
    :param out: the experiment folder
    :return: every run it expects (from ``grid.json``, plus any ``*/seed_*/spec.json`` found), with its status;
        each run's folder is taken as ``out/<model>/seed_<n>``, wherever it was when it ran
    """
    out = Path(out)
    specs: dict[str, dict[str, Any]] = {}
    for data in (read_json(out / GRID_FILE) or {}).get("runs", []):
        specs[_run_key(data)] = data
    for path in sorted(out.glob(f"*/seed_*/{SPEC_FILE}")):
        data = read_json(path)
        if data is not None:
            specs[_run_key(data)] = data  # the run's own spec wins: it is what trained
    records = []
    for key, data in specs.items():
        spec = dataclasses.replace(RunSpec(**data), run_dir=str(out / key))
        records.append(RunRecord(spec, *_run_status(out / key)))
    return records


def recorded_heads(out: str | os.PathLike) -> dict[str, Any]:
    """
    :param out: the experiment folder
    :return: suite -> the head counts its ``run`` commands asked for (from ``grid.json``), for :func:`select_columns`
    """
    return {name: entry.get("heads", []) for name, entry in (read_json(Path(out) / GRID_FILE) or {}).get("suites", {}).items()}


def report_target(out: str | os.PathLike, suite: str | None, report_dir: str | os.PathLike | None) -> Path:
    """
    :param out: the experiment folder
    :param suite: the suite reported, if one
    :param report_dir: where the user asked for the files (``None``: the default)
    :return: the folder the report files go to (created): ``report_dir``, else ``out/report-<suite>``, else ``out``
    """
    target = Path(report_dir) if report_dir is not None else (Path(out) / f"report-{suite}" if suite else Path(out))
    target.mkdir(parents=True, exist_ok=True)
    return target


def select_columns(records: Sequence[RunRecord], suite: str | None, extra_heads: dict[str, Any]) -> list[Column]:
    """
    :param records: the folder's runs
    :param suite: keep this suite's columns (``None``: every model in the folder, with its own title)
    :param extra_heads: suite -> head counts recorded in ``grid.json``
    :return: the columns in table order (the suite's variant order, then K)
    """
    columns: dict[tuple[str, str], Column] = {}
    for record in records:
        if suite is None:
            variant, label = None, record.spec.label
        else:
            found = suite_columns(record.spec, extra_heads).get(suite)
            if found is None:
                continue
            variant, label = found
        key = (record.spec.env_id, record.spec.model)
        columns.setdefault(key, Column(record.spec.model, label, [], variant)).records.append(record)
    if suite is None:
        return list(columns.values())
    order = SUITES[suite].variants

    def rank(column: Column) -> tuple[int, int]:
        return order.index(column.variant or ""), column.records[0].spec.n_heads or 0

    return sorted(columns.values(), key=rank)


def resolve_baseline(name: str, columns: Sequence[Column], records: Sequence[RunRecord]) -> str | None:
    """
    :param name: a model id (``dbddpg-k5``), or a variant of the report's suite with or without its K (``none``,
        ``none-k5``)
    :param columns: the report's columns
    :param records: all runs of the folder (the baseline need not be a column, e.g. DDPG for the confidence suite)
    :return: the baseline's model id, ``None`` when the folder has no such model
    """
    models = {record.spec.model for record in records}
    if name in models:
        return name
    match = re.fullmatch(r"(.+?)(?:-k(\d+))?", name)
    variant, n_heads = (match.group(1), match.group(2)) if match else (name, None)
    for column in columns:
        if column.variant == variant and (n_heads is None or column.records[0].spec.n_heads == int(n_heads)):
            return column.model
    return None


def _fmt(value: float | None, digits: int = 0) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{digits}f}"


def _crossing(value: float | None, crossed: int, n_seeds: int) -> str:
    if value is None:
        return f"never (0/{n_seeds})"
    return _fmt(value) + ("" if crossed == n_seeds else f" ({crossed}/{n_seeds})")


def _used_records(column: Column, partial: bool) -> list[RunRecord]:
    """The runs whose episodes a column's metrics use: the finished ones, and with ``partial`` the others too."""
    return [record for record in column.records if record.status == "finished" or partial]


def format_table(
    columns: Sequence[Column],
    metrics: dict[str, dict[str, ModelMetrics]],
    thresholds: dict[str, tuple[float | None, float | None]],
    records: Sequence[RunRecord],
    window: int | None,
    baseline: str | None,
    partial_models: set[str],
    used: set[str] | None = None,
    baseline_name: str = BASELINE,
) -> str:
    """
    Table 1's layout: one row per (env, metric), one column per model.

    :param columns: the models, in order
    :param metrics: env -> model -> metrics
    :param thresholds: env -> (Episode, Speed Up) thresholds
    :param records: the runs to account for (those of the columns and of the baseline)
    :param window: the running-average window used
    :param baseline: the model Speed Up is measured against (``None``: not in the folder)
    :param partial_models: models whose numbers include unfinished runs (marked with a dagger)
    :param used: the runs whose episodes the numbers use, as ``env_id:model/seed_N`` (default: the finished ones)
    :param baseline_name: the baseline asked for (named when it is not in the folder)
    :return: Markdown
    """
    models = list(dict.fromkeys(column.model for column in columns))
    titles = {
        column.model: column.label + (f" {PARTIAL_MARK}" if column.model in partial_models else "") for column in columns
    }
    lines = ["| Env. | Metric | " + " | ".join(titles[model] for model in models) + " |", "|---|---|" + "---|" * len(models)]
    expected = {
        (record.spec.env_id, record.spec.model): sum(
            other.spec.env_id == record.spec.env_id and other.spec.model == record.spec.model for other in records
        )
        for record in records
    }
    for env_id, env_metrics in metrics.items():
        rows: dict[str, list[str]] = {name: [] for name in ("Avg Return", "Max Return", "Episode", "Speed Up", "E", "Seeds")}
        for model in models:
            entry = env_metrics.get(model)
            n_expected = expected.get((env_id, model), 0)
            if entry is None:
                for name, row in rows.items():
                    row.append(f"0/{n_expected}" if name == "Seeds" else "n/a")
                continue
            rows["Avg Return"].append(f"{_fmt(entry.avg_return)} ± {_fmt(entry.avg_return_std)}")
            rows["Max Return"].append(_fmt(entry.max_return))
            episode, lower = thresholds[env_id]
            rows["Episode"].append("-" if episode is None else _crossing(entry.episode, entry.episode_crossed, entry.n_seeds))
            rows["Speed Up"].append("(baseline)" if model == baseline else _fmt(entry.speed_up, 2))
            rows["E"].append("-" if lower is None else _crossing(entry.speedup_episode, entry.speedup_crossed, entry.n_seeds))
            rows["Seeds"].append(f"{entry.n_seeds}/{n_expected}")
        for index, (name, row) in enumerate(rows.items()):
            lines.append(f"| {env_id if index == 0 else ''} | {name} | " + " | ".join(row) + " |")
    lines.append("")
    running = f"last {window} episodes" if window else "all episodes so far"
    reference = f"E_{baseline}" if baseline else "E_baseline"
    for env_id, (episode, lower) in thresholds.items():
        if episode is None or lower is None:
            lines.append(
                f"- {env_id}: no paper threshold for this env: pass `report --threshold T --speedup-threshold T_LOW` "
                "for Episode, E and Speed Up."
            )
            if episode is None and lower is None:
                continue
        lines.append(
            f"- {env_id}: **Episode** = first training episode with return >= {_fmt(episode)}; **E** = first episode "
            f"whose running average return ({running}) >= {_fmt(lower)}; **Speed Up** = 1 - E/{reference}."
        )
    if baseline is None:
        lines.append(
            f"- No Speed Up: its baseline `{baseline_name}` is not in this folder (`report --baseline MODEL` picks another)."
        )
    lines.append(
        "- Avg Return: mean ± std (ddof=0) over seeds of each seed's mean training-episode return; Max Return: best "
        "single training episode over all seeds; Episode and E: mean over the seeds that crossed, (k/n) when not all "
        "did; Speed Up is '-' when the model's or the baseline's running average never crossed; Seeds: runs used / "
        "runs expected."
    )
    if used is None:
        used = {_record_id(record) for record in records if record.status == "finished"}
    lines += _not_included(records, used, bool(partial_models))
    return "\n".join(lines) + "\n"


def _record_id(record: RunRecord) -> str:
    return f"{record.spec.env_id}:{record.spec.key}"


def _not_included(records: Sequence[RunRecord], used: set[str], partial: bool) -> list[str]:
    """The footnotes on the runs not in the numbers, and on the unfinished ones that are (partial)."""
    lines = []
    in_partial = [record for record in records if record.status != "finished" and _record_id(record) in used]
    left_out = [record for record in records if _record_id(record) not in used]
    if in_partial:
        lines += ["", f"**{PARTIAL_MARK} Partial: {len(in_partial)} unfinished runs are included with the episodes so far:**"]
        lines += [""] + [_describe(record) for record in in_partial]
    if left_out:
        lines += ["", f"**Not included ({len(left_out)} runs):**", ""]
        lines += [_describe(record) for record in left_out]
        if not partial and any(record.status not in ("missing", "finished") for record in left_out):
            lines += ["", "(`report --partial` computes the metrics of unfinished runs from their episodes so far.)"]
    return lines


def _describe(record: RunRecord) -> str:
    if record.status == "missing":
        return f"- `{record.spec.env_id}` `{record.spec.key}`: not started"
    if record.status == "finished":
        return f"- `{record.spec.env_id}` `{record.spec.key}`: finished, but no complete episode"
    detail = f"{record.step}/{record.spec.timesteps} steps"
    if record.error:
        detail += f": {record.error}"
    return f"- `{record.spec.env_id}` `{record.spec.key}`: {record.status} ({detail})"


@dataclasses.dataclass
class _Results:
    metrics: dict[str, dict[str, ModelMetrics]]
    curves: dict[str, list[Curve]]
    confidence: dict[str, list[tuple[int, Any]]]
    partial: set[str]
    used: set[str]


def _compute(
    columns: Sequence[Column],
    baseline_columns: Sequence[Column],
    thresholds: dict[str, tuple[float | None, float | None]],
    window: int | None,
    partial: bool,
) -> _Results:
    """Every column's metrics (without Speed Up), curves and confidence panels, per env."""
    envs = list(thresholds)
    results = _Results({env_id: {} for env_id in envs}, {env_id: [] for env_id in envs}, {}, set(), set())
    for column in [*columns, *baseline_columns]:
        for env_id in envs:
            used = [record for record in _used_records(column, partial) if record.spec.env_id == env_id]
            frames = [(record, logs.read_monitor(record.spec.run_dir)) for record in used]
            frames = [(record, frame) for record, frame in frames if len(frame)]
            if not frames:
                continue
            results.used.update(_record_id(record) for record, _ in frames)
            if any(record.status != "finished" for record, _ in frames):
                results.partial.add(column.model)
            returns = [frame["r"].to_numpy(dtype=float) for _, frame in frames]
            entry = model_metrics(
                returns, *thresholds[env_id], window=window, seeds=[record.spec.seed for record, _ in frames]
            )
            for seed_entry, (record, _) in zip(entry.per_seed, frames, strict=True):
                seed_entry.update(status=record.status, steps=record.step, timesteps=record.spec.timesteps)
            results.metrics[env_id][column.model] = entry
            if column in baseline_columns:
                continue
            title = column.label + (" (partial)" if column.model in results.partial else "")
            legend = column.label + (" (partial: unfinished runs)" if column.model in results.partial else "")
            results.curves[env_id].append(Curve(legend, returns, [frame["l"].to_numpy(dtype=float) for _, frame in frames]))
            if any(_is_adaptive(record.spec) for record, _ in frames):
                panels = [(record.spec.seed, logs.read_progress(record.spec.run_dir)) for record, _ in frames]
                panels = [(seed, frame) for seed, frame in panels if any(col.startswith("confidence/head_") for col in frame)]
                if panels:
                    results.confidence[f"{title}, {env_id}"] = panels
    return results


def evaluation_report(
    columns: Sequence[Column],
    baseline: str | None,
    step: int | None,
    partial: bool,
    reps: int = evaluation.DEFAULT_REPS,
    last: int = 1,
) -> tuple[str, dict[str, Any], dict[str, Any]]:
    """
    The deterministic evaluations' statistics: per env and model, the IQM of the runs' evaluation returns at ``step``
    with its 95% stratified-bootstrap interval, mean ± std, and the probability of improvement over ``baseline``.

    :param columns: the models (and the baseline's column, if it is not one of them)
    :param baseline: the baseline's model id (``None``: no probability of improvement)
    :param step: the evaluation step (default: per env, the last one every used run has)
    :param partial: also use unfinished runs that have an evaluation at the step
    :param reps: bootstrap resamples of the intervals (the curves' use a fifth)
    :param last: a run's score is the mean of its last ``last`` evaluations up to the step (1: the step's alone)
    :return: Markdown (empty when no run has evaluations), JSON data, and the curves to plot
    """
    rows: dict[str, list[tuple[Column, list[RunRecord], list[tuple[np.ndarray, np.ndarray]]]]] = {}
    for column in columns:
        for env_id in dict.fromkeys(record.spec.env_id for record in column.records):
            used = [r for r in _used_records(column, partial) if r.spec.env_id == env_id]
            found = [(record, evaluation.read_run(record.spec.run_dir)) for record in used]
            found = [(record, run) for record, run in found if len(run[0])]
            if found:
                rows.setdefault(env_id, []).append((column, [record for record, _ in found], [run for _, run in found]))
    if not rows:
        return "", {}, {}
    lines = [
        "| Env. | Model | Step | Runs | IQM [95% CI] | Mean ± std | P(improvement) [95% CI] |",
        "|---|---|---|---|---|---|---|",
    ]
    data: dict[str, Any] = {}
    curves: dict[str, Any] = {}
    for env_id, env_rows in rows.items():
        at = step if step is not None else min(max(evaluation.common_steps(runs)) for _, _, runs in env_rows)
        # the runs evaluated at that step (an unfinished run may not be there yet); a model without any is left out
        env_rows = [
            (column, [record for record, run in kept], [run for _, run in kept])
            for column, records, runs in env_rows
            if (kept := [(record, run) for record, run in zip(records, runs) if at in evaluation.common_steps([run])])
        ]
        scores = {column.model: evaluation.run_scores(runs, at, last) for column, _, runs in env_rows}
        reference = scores.get(baseline) if baseline is not None else None
        # the steps a score averages (every run evaluates on the same grid: its first and last steps name the window)
        window = [s for s in evaluation.common_steps([run for _, _, runs in env_rows for run in runs]) if s <= at][-last:]
        at_text = str(at) if last == 1 else f"{window[0]}-{at}"
        data[env_id] = {
            "step": at,
            "steps_averaged": window,
            "baseline": baseline if reference is not None else None,
            "models": {},
        }
        curves[env_id] = []
        for index, (column, records, runs) in enumerate(env_rows):
            values = scores[column.model]
            estimate = evaluation.iqm(values, reps=reps)
            improvement = None
            if reference is not None and column.model != baseline:
                improvement = evaluation.probability_of_improvement(values, reference, reps=reps)
            data[env_id]["models"][column.model] = {
                "label": column.label,
                "seeds": [record.spec.seed for record in records],
                "scores": values.tolist(),
                "iqm": dataclasses.asdict(estimate),
                "mean": float(values.mean()),
                "std": float(values.std(ddof=0)),
                "probability_of_improvement": None if improvement is None else dataclasses.asdict(improvement),
            }
            cell = "(baseline)" if column.model == baseline else (improvement.format(2) if improvement else "-")
            lines.append(
                f"| {env_id if index == 0 else ''} | {column.label} | {at_text} | {len(values)} | {estimate.format()} | "
                f"{values.mean():.0f} ± {values.std(ddof=0):.0f} | {cell} |"
            )
            steps = [s for s in evaluation.common_steps(runs) if s <= at]
            curve = evaluation.iqm_curve(runs, steps, reps=max(1, reps // 5))
            curves[env_id].append((column.label, steps, [(e.value, e.low, e.high) for e in curve]))
    episodes = "the mean return of its deterministic evaluation episodes"
    score = f"{episodes} at the step"
    if last > 1:
        score = f"the mean of its last {last} evaluations up to the step, each {episodes}"
    lines += [
        "",
        f"- A run's score: {score} (SB3's EvalCallback). "
        "IQM: interquartile mean over runs; [95% CI]: stratified bootstrap (rliable); Mean ± std: over runs (ddof=0).",
        f"- P(improvement): probability that a run of the model scores higher than a run of `{baseline}` (rliable)."
        if baseline is not None
        else "- No P(improvement): no baseline (`report --baseline MODEL`).",
    ]
    return "\n".join(lines) + "\n", data, curves


def make_report(
    out: str | os.PathLike,
    thresholds: dict[str, tuple[float | None, float | None]] | None = None,
    window: int | None = DEFAULT_WINDOW,
    baseline: str | None = None,
    x_axis: str = "both",
    suite: str | None = None,
    partial: bool = False,
    report_dir: str | os.PathLike | None = None,
    eval_step: int | None = None,
    extra: Sequence[str | os.PathLike] = (),
    bootstrap_reps: int = evaluation.DEFAULT_REPS,
    eval_last: int = 1,
) -> dict[str, Any]:
    """
    Compute the metrics of an experiment folder's runs and write the report files.

    :param out: the experiment folder
    :param thresholds: env -> (Episode, Speed Up) thresholds, overriding the paper's (Hopper, Walker2d)
    :param window: running-average window for Speed Up and the curves (``None``: cumulative mean)
    :param baseline: the model Speed Up is measured against: a model id or a variant of ``suite`` (default: the
        suite's baseline, e.g. ``none`` for the confidence suite; ``ddpg`` without a suite)
    :param x_axis: x-axis of ``curves.png``: ``"episodes"``, ``"timesteps"`` or ``"both"`` (two panels per env)
    :param suite: report only this suite's models, with its column titles (default: every model in the folder)
    :param partial: also use the episodes of unfinished runs (marked as partial); default: finished runs only
    :param report_dir: where to write (default: ``out``, or ``out/report-<suite>`` with a suite)
    :param eval_step: the evaluation step of ``evaluation.md`` (default: the last one every run has)
    :param extra: more experiment folders whose runs join the report (e.g. baselines trained for longer, read at
        ``eval_step``); a run (env, model, seed) may be in one folder only
    :param bootstrap_reps: bootstrap resamples of ``evaluation.md``'s intervals
    :param eval_last: ``evaluation.md`` scores a run by the mean of its last ``eval_last`` evaluations up to
        ``eval_step`` (1: the step's alone)
    :return: the data written to ``metrics.json``
    """
    out = Path(out)
    if suite is not None and suite not in SUITES:
        raise ValueError(f"Unknown suite {suite!r}; choose from {sorted(SUITES)}")
    records = collect_runs(out)
    for folder in extra:
        more = collect_runs(folder)
        if not more:
            raise FileNotFoundError(f"No runs found in {folder}")
        taken = {(record.spec.env_id, record.spec.key) for record in records}
        clash = sorted(key for record in more if (key := (record.spec.env_id, record.spec.key)) in taken)
        if clash:
            raise ValueError(f"{folder} and the other folders both hold the runs {clash[:3]}: report them separately")
        records += more
    if not records:
        raise FileNotFoundError(f"No runs found in {out} (expected {GRID_FILE} or */seed_*/{SPEC_FILE})")
    columns = select_columns(records, suite, recorded_heads(out))
    if not columns:
        raise ValueError(f"No run of the {suite!r} suite in {out}")
    baseline_name = baseline or (SUITES[suite].baseline if suite else BASELINE)
    baseline_model = resolve_baseline(baseline_name, columns, records)
    shown = {column.model for column in columns}
    baseline_columns = [] if baseline_model is None or baseline_model in shown else select_columns(records, None, {})
    baseline_columns = [column for column in baseline_columns if column.model == baseline_model]
    envs = list(dict.fromkeys(record.spec.env_id for column in columns for record in column.records))
    resolved = {env_id: (thresholds or {}).get(env_id, paper_thresholds(env_id)) for env_id in envs}

    results = _compute(columns, baseline_columns, resolved, window, partial)
    metrics, curves, confidence, partial_models = results.metrics, results.curves, results.confidence, results.partial
    if baseline_model is not None:
        for env_id in envs:
            add_speed_ups(metrics[env_id], baseline_model)

    target = report_target(out, suite, report_dir)
    accounted = [record for column in [*columns, *baseline_columns] for record in column.records]
    files = ["table.md", "metrics.json"]
    table = format_table(
        columns, metrics, resolved, accounted, window, baseline_model, partial_models, results.used, baseline_name
    )
    if suite:
        table = f"Suite: **{suite}** (from `{out}`)\n\n" + table
    (target / "table.md").write_text(table)
    if any(curves.values()):
        plot_curves(
            {env_id: env_curves for env_id, env_curves in curves.items() if env_curves}, target / "curves.png", x_axis, window
        )
        files.append("curves.png")
    if confidence:
        plot_confidence(confidence, target / "confidence.png")
        files.append("confidence.png")
    evaluation_table, evaluation_data, evaluation_curves = evaluation_report(
        [*columns, *baseline_columns], baseline_model, eval_step, partial, bootstrap_reps, eval_last
    )
    if evaluation_table:
        title = f"Suite: **{suite}** (from `{out}`)\n\n" if suite else ""
        (target / "evaluation.md").write_text(title + evaluation_table)
        plot_evaluations(evaluation_curves, target / "evaluation.png")
        files += ["evaluation.md", "evaluation.png"]
    data = {
        "suite": suite,
        "thresholds": {env_id: {"episode": pair[0], "speed_up": pair[1]} for env_id, pair in resolved.items()},
        "window": window,
        "baseline": baseline_model,
        "std_ddof": 0,
        "partial": sorted(partial_models),
        "labels": {column.model: column.label for column in columns},
        "columns": [column.model for column in columns],
        "metrics": {
            env_id: {model: dataclasses.asdict(entry) for model, entry in env_metrics.items()}
            for env_id, env_metrics in metrics.items()
        },
        "runs": [
            {
                "env_id": record.spec.env_id,
                "model": record.spec.model,
                "seed": record.spec.seed,
                "status": record.status,
                "step": record.step,
                "timesteps": record.spec.timesteps,
                "error": record.error,
            }
            for record in accounted
        ],
        "not_included": [_record_id(record) for record in accounted if _record_id(record) not in results.used],
        "evaluation": evaluation_data,
        "files": files,
        "report_dir": str(target),
    }
    (target / "metrics.json").write_text(json.dumps(data, indent=2, default=_json_default))
    return data


def _is_adaptive(spec: RunSpec) -> bool:
    """Whether a run uses self-adaptive confidence: given explicitly, else by its preset, else SOUP's default."""
    from sb3_soup.presets import PRESETS, normalize_preset_name

    confidence = spec.hyperparams.get("confidence")
    preset = spec.hyperparams.get("preset")
    if confidence is None:
        confidence = PRESETS[normalize_preset_name(preset)]["confidence"] if preset is not None else "adaptive"
    return spec.algo == "soup" and str(confidence).lower() == "adaptive"


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"Not JSON serialisable: {type(value)}")
