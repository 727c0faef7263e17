"""
The screening suite's report (``screen report``): each model's runs on the tasks of
:data:`~sb3_soup.experiments.grid.SCREEN_TASKS`, scored, normalised per task and aggregated over tasks with rliable.

- A run's **score**: the mean return of its deterministic evaluation at the task's budget (its last one). Only finished
  runs trained with the task's protocol (budget, warm-up, evaluation frequency and episodes) have one.
- **Normalised** per task: ``(score - random) / (reference - random)``, where ``random`` is the mean return of a uniform
  random policy (:func:`random_policy_score`: the runs' evaluation protocol, :data:`RANDOM_EPISODES` episodes, seed
  :data:`RANDOM_SEED`) and ``reference`` the mean score of the reference's runs (TD3 with the RL Zoo's settings), so
  0 is random and 1 is TD3 on every task.
- **Aggregate**, per model over the tasks where it is complete (every expected seed scored) and the reference is too:
  rliable's IQM and mean of the normalised scores with stratified-bootstrap 95% intervals, the probability of
  improvement over TD3 and over DDPG, or over the models asked for (over the tasks both models have complete), the
  worst task's mean, and performance profiles. Without ``partial``, a model joins the aggregate only once it is
  complete on every task.

Missing, unfinished, failed or off-protocol runs are listed, never dropped silently. The random policy's scores are
cached in ``ROOT/random_scores.json`` (written by ``screen run``); the report reads them there or in its own folder,
and writes those it had to compute to its own folder only (the screen's folder may be read-only to it).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sb3_soup.experiments import evaluation
from sb3_soup.experiments.grid import (
    SCREEN_BASELINES,
    SCREEN_EVAL_EPISODES,
    SCREEN_EVAL_FREQ,
    SCREEN_REFERENCE,
    ScreenTask,
    screen_tasks,
)
from sb3_soup.experiments.report import RunRecord, collect_runs
from sb3_soup.experiments.runner import read_json, write_json

RANDOM_SCORES_FILE = "random_scores.json"
RANDOM_EPISODES = 100
RANDOM_SEED = 0
# By default the probability of improvement is reported over these two (the reference, and SB3's DDPG as the Zoo
# trains it); ``screen report --improvement-over`` names others (e.g. SOUP's defaults, to weigh a candidate against them).
IMPROVEMENT_OVER = (SCREEN_REFERENCE, "ddpg_zoo")
REPORT_FILE = "screen.md"
DATA_FILE = "screen.json"
PARTIAL_MARK = "†"


class RandomPolicy:
    """
    Uniform random actions, in the shape SB3's ``evaluate_policy`` asks a model for them.

    :param action_space: the env's action space
    :param seed: the seed of its sampler
    """

    def __init__(self, action_space: Any, seed: int) -> None:
        self.action_space = action_space
        self.action_space.seed(seed)

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None, deterministic: bool = False) -> Any:
        """:return: one random action per env, and ``state`` unchanged"""
        n_envs = 1 if episode_start is None else len(episode_start)
        return np.stack([self.action_space.sample() for _ in range(n_envs)]), state


def random_policy_score(env_id: str, episodes: int = RANDOM_EPISODES, seed: int = RANDOM_SEED) -> dict[str, Any]:
    """
    The mean return of uniform random actions, with the runs' evaluation protocol (a ``Monitor``-wrapped
    ``gym.make(env_id)`` in a ``DummyVecEnv``, SB3's ``evaluate_policy``), on ``episodes`` episodes seeded by ``seed``.

    :param env_id: the task
    :param episodes: the episodes
    :param seed: the seed of the env and of the actions
    :return: ``{"mean", "std", "episodes", "seed", "returns"}``
    """
    import gymnasium as gym
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    env = DummyVecEnv([lambda: Monitor(gym.make(env_id))])
    try:
        env.seed(seed)
        returns, _ = evaluate_policy(
            RandomPolicy(env.action_space, seed),  # type: ignore[arg-type]
            env,
            n_eval_episodes=episodes,
            deterministic=True,
            return_episode_rewards=True,
            warn=False,
        )
    finally:
        env.close()
    values = np.asarray(returns, dtype=float)
    return {"mean": float(values.mean()), "std": float(values.std()), "episodes": episodes, "seed": seed,
            "returns": values.tolist()}  # fmt: skip


def random_scores(
    env_ids: Sequence[str],
    read_from: Sequence[str | os.PathLike],
    write_to: str | os.PathLike | None,
    episodes: int = RANDOM_EPISODES,
    seed: int = RANDOM_SEED,
) -> dict[str, dict[str, Any]]:
    """
    The random policy's score of each task, from the first cache that has it (computed with the same episodes and
    seed), else computed and added to ``write_to``'s cache.

    :param env_ids: the tasks
    :param read_from: folders whose ``random_scores.json`` may hold them, in order
    :param write_to: the folder whose ``random_scores.json`` gets the ones computed here (``None``: not cached)
    :param episodes: see :func:`random_policy_score`
    :param seed: see :func:`random_policy_score`
    :return: env id -> :func:`random_policy_score`'s result
    """
    caches = [read_json(Path(folder) / RANDOM_SCORES_FILE) or {} for folder in read_from]
    scores: dict[str, dict[str, Any]] = {}
    computed: dict[str, dict[str, Any]] = {}
    for env_id in env_ids:
        found = [
            cache[env_id]
            for cache in caches
            if env_id in cache and (cache[env_id].get("episodes"), cache[env_id].get("seed")) == (episodes, seed)
        ]
        scores[env_id] = found[0] if found else computed.setdefault(env_id, random_policy_score(env_id, episodes, seed))
    if computed and write_to is not None:
        path = Path(write_to) / RANDOM_SCORES_FILE
        path.parent.mkdir(parents=True, exist_ok=True)
        write_json(path, {**(read_json(path) or {}), **computed})
    return scores


def off_protocol(record: RunRecord, task: ScreenTask) -> str | None:
    """
    :param record: a run found in the task's folder
    :param task: the task
    :return: how the run differs from the task's protocol, ``None`` when it does not
    """
    spec = record.spec
    found = {
        "timesteps": (spec.timesteps, task.timesteps),
        "eval_freq": (spec.eval_freq, SCREEN_EVAL_FREQ),
        "eval_episodes": (spec.eval_episodes, SCREEN_EVAL_EPISODES),
        "learning_starts": (spec.hyperparams.get("learning_starts"), task.learning_starts),
    }
    differences = [f"{name} {value} (the task's: {wanted})" for name, (value, wanted) in found.items() if value != wanted]
    return ", ".join(differences) or None


def final_score(record: RunRecord) -> float | None:
    """
    :param record: a run
    :return: the mean return of its evaluation at its budget; ``None`` unless it finished and has that evaluation
    """
    if record.status != "finished":
        return None
    steps, means = evaluation.read_run(record.spec.run_dir)
    where = np.flatnonzero(steps == record.spec.timesteps)
    return float(means[where[0]]) if where.size else None


@dataclasses.dataclass
class Cell:
    """
    One model's runs on one task.

    :param scores: seed -> final score, for the runs that have one
    :param expected: the seeds the model should have
    :param notes: seed -> why it has no score (not started, running at step s, failed, off the task's protocol...)
    :param run_dirs: seed -> the folder of the run that has its score
    :param others: seed -> final score of the runs of other seeds than ``expected`` (``--seeds`` narrowed them out):
        left out of the model's tables, curves and aggregate; the reference model's count in the task's reference
    """

    scores: dict[int, float]
    expected: list[int]
    notes: dict[int, str]
    run_dirs: dict[int, str] = dataclasses.field(default_factory=dict)
    others: dict[int, float] = dataclasses.field(default_factory=dict)

    @property
    def complete(self) -> bool:
        """Whether every expected seed has a score."""
        return all(seed in self.scores for seed in self.expected)


def _note(record: RunRecord, score: float | None) -> str:
    """Why a run has no score."""
    if record.status == "finished" and score is None:
        return "finished without an evaluation at its budget"
    if record.status == "missing":
        return "not started"
    text = f"{record.status} at step {record.step}/{record.spec.timesteps}"
    return text + (f": {record.error}" if record.error else "")


def collect_screen(
    root: str | os.PathLike,
    tasks: Sequence[ScreenTask],
    models: Sequence[str] | None = None,
    seeds: Sequence[int] | None = None,
) -> tuple[list[str], dict[str, str], dict[str, dict[str, Cell]]]:
    """
    :param root: the screen's folder
    :param tasks: the tasks
    :param models: report these model ids only (default: every model found, the baselines first)
    :param seeds: the seeds each model should have (default: per model, every seed any task's folder has for it)
    :return: the model ids in report order, their labels, and model -> env id -> its :class:`Cell`
    """
    found: dict[str, dict[str, list[RunRecord]]] = {}
    labels: dict[str, str] = {}
    for task in tasks:
        folder = Path(root) / task.env_id
        for record in collect_runs(folder) if folder.is_dir() else []:
            found.setdefault(record.spec.model, {}).setdefault(task.env_id, []).append(record)
            labels.setdefault(record.spec.model, record.spec.label)
    if models is not None:
        unknown = [model for model in models if model not in found]
        if unknown:
            raise ValueError(f"No runs of {unknown} in {root} (it has {sorted(found)})")
        order = list(models)
    else:
        order = [model for model in SCREEN_BASELINES if model in found] + [m for m in found if m not in SCREEN_BASELINES]
    cells: dict[str, dict[str, Cell]] = {}
    for model in order:
        runs = found[model]
        expected = sorted(seeds) if seeds is not None else sorted({r.spec.seed for records in runs.values() for r in records})
        cells[model] = {}
        for task in tasks:
            cell = Cell({}, list(expected), {})
            for record in runs.get(task.env_id, []):
                differs = off_protocol(record, task)
                score = None if differs else final_score(record)
                if score is not None and record.spec.seed not in expected:
                    cell.others[record.spec.seed] = score
                elif score is not None:
                    cell.scores[record.spec.seed] = score
                    cell.run_dirs[record.spec.seed] = record.spec.run_dir
                elif record.spec.seed in expected:
                    cell.notes[record.spec.seed] = f"off the task's protocol: {differs}" if differs else _note(record, score)
            for seed in expected:
                if seed not in cell.scores:
                    cell.notes.setdefault(seed, "not started")
            cells[model][task.env_id] = cell
    return order, labels, cells


@dataclasses.dataclass
class Screen:
    """
    A screen's runs, scored, with what normalises them.

    :param root: its folder
    :param tasks: its tasks
    :param models: the model ids, in report order
    :param labels: model id -> title
    :param cells: model id -> env id -> its runs there
    :param random: env id -> the random policy's score (:func:`random_policy_score`)
    :param references: env id -> ``{"mean", "runs", "complete"}`` of the reference's scores, where it has any
    """

    root: Path
    tasks: list[ScreenTask]
    models: list[str]
    labels: dict[str, str]
    cells: dict[str, dict[str, Cell]]
    random: dict[str, dict[str, Any]]
    references: dict[str, dict[str, Any]]

    @property
    def env_ids(self) -> list[str]:
        """The tasks' env ids."""
        return [task.env_id for task in self.tasks]

    def normalise(self, env_id: str, score: float) -> float | None:
        """
        :return: the score normalised between the random policy (0) and the reference (1); ``None`` without a reference,
            or with one that does no better than the random policy at the task's budget (see :meth:`unusable`)
        """
        reference, random = self.references.get(env_id), self.random[env_id]["mean"]
        if reference is None or self.unusable(env_id):
            return None
        return (score - random) / (reference["mean"] - random)

    def unusable(self, env_id: str) -> bool:
        """
        :return: whether the task's reference (its mean score) does no better than the random policy: 1 would then
            mean random or worse, and the scale of the normalised scores would be meaningless, so the task normalises
            nothing (its budget is too short for the reference to learn)
        """
        reference = self.references.get(env_id)
        return reference is not None and reference["mean"] <= self.random[env_id]["mean"]

    def aggregate_tasks(self, model: str, partial: bool) -> list[str]:
        """:return: the tasks a model is aggregated over: complete for it, with a reference (complete, unless partial)"""
        return [
            env_id
            for env_id in self.env_ids
            if self.cells[model][env_id].complete
            and env_id in self.references
            and (self.references[env_id]["complete"] or partial)
            and self.normalise(env_id, 0.0) is not None
        ]

    def matrix(self, model: str, env_ids: Sequence[str]) -> np.ndarray:
        """:return: ``(seeds, tasks)`` the model's normalised scores on tasks where it is complete"""
        seeds = self.cells[model][env_ids[0]].expected
        return np.array(
            [[self.normalise(env_id, self.cells[model][env_id].scores[seed]) for env_id in env_ids] for seed in seeds],
            dtype=float,
        )

    def mean_normalised(self, model: str, env_id: str) -> float | None:
        """:return: the mean normalised score of the model's scored runs on the task (``None``: none, or no reference)"""
        scores = list(self.cells[model][env_id].scores.values())
        return self.normalise(env_id, float(np.mean(scores))) if scores else None  # normalising is linear


def aggregate_screen(
    screen: Screen, partial: bool, reps: int, improvement_over: Sequence[str]
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """
    :param screen: the screen
    :param partial: see :func:`screen_report`
    :param reps: bootstrap resamples
    :param improvement_over: the models each model's probability of improvement is computed over (see :func:`screen_report`)
    :return: model -> its aggregate (the IQM and mean with their intervals, the probabilities of improvement, the
        worst task), for the models in it; and model -> the ``(seeds, tasks)`` matrix it was computed from
    """
    tasks = {model: screen.aggregate_tasks(model, partial) for model in screen.models}
    entered = [m for m in screen.models if tasks[m] and (partial or len(tasks[m]) == len(screen.tasks))]
    matrices = {model: screen.matrix(model, tasks[model]) for model in entered}
    aggregate: dict[str, Any] = {}
    for model in entered:
        matrix = matrices[model]
        per_task = dict(zip(tasks[model], matrix.mean(axis=0).tolist(), strict=True))
        worst = min(per_task, key=per_task.__getitem__)
        improvement = {}
        for other in improvement_over:
            if other == model or other not in screen.cells or (not partial and other not in entered):
                continue
            shared = [env_id for env_id in tasks[model] if env_id in tasks[other]]
            if shared:
                mine = matrix[:, [tasks[model].index(env_id) for env_id in shared]]
                estimate = evaluation.probability_of_improvement(mine, screen.matrix(other, shared), reps=reps)
                improvement[other] = {**dataclasses.asdict(estimate), "tasks": shared}
        estimates = evaluation.aggregates(matrix, ("iqm", "mean"), reps=reps)
        aggregate[model] = {
            "label": screen.labels[model],
            "tasks": tasks[model],
            "runs": int(matrix.size),
            "complete": len(tasks[model]) == len(screen.tasks),
            **{name: dataclasses.asdict(estimate) for name, estimate in estimates.items()},
            "probability_of_improvement": improvement,
            "per_task_mean": per_task,
            "worst_task": {"env_id": worst, "normalised": per_task[worst]},
        }
    return aggregate, matrices


def screen_report(
    root: str | os.PathLike,
    report_dir: str | os.PathLike | None = None,
    tasks: Sequence[str] | None = None,
    models: Sequence[str] | None = None,
    seeds: Sequence[int] | None = None,
    partial: bool = False,
    reps: int = evaluation.DEFAULT_REPS,
    random_episodes: int = RANDOM_EPISODES,
    improvement_over: Sequence[str] | None = None,
) -> dict[str, Any]:
    """
    Score, normalise and aggregate a screen's runs; write ``screen.md``, ``screen.json`` and the figures, each with the
    JSON behind it next to it: ``aggregate.png`` (IQM and mean), ``improvement.png`` (probabilities of improvement)
    and ``performance_profiles.png``; and ``curves.png``, each task's learning curves (per model, the IQM over its
    scored runs of their evaluation returns, with 95% intervals from a twentieth of ``reps``: rliable's bootstrap costs
    milliseconds per resample, and a curve has one per evaluation step), which need no aggregate.

    :param root: the screen's folder (``ROOT/<env_id>/<model>/seed_<n>``); only read
    :param report_dir: where to write (default: ``root/report``)
    :param tasks: narrow the suite to these env ids
    :param models: report these model ids only (default: every model in ``root``)
    :param seeds: the seeds every model should have (default: per model, those its runs have on any task)
    :param partial: aggregate each model over the tasks where it is complete, even when it is not complete on all
        (marked); default: only models complete on every task enter the aggregate
    :param reps: bootstrap resamples of the intervals (the performance profiles' bands use a fifth, the curves a twentieth)
    :param random_episodes: the random policy's episodes per task
    :param improvement_over: the models each model's probability of improvement is over, among the reported ones
        (default: :data:`IMPROVEMENT_OVER`, TD3 and DDPG with the RL Zoo's settings, those the report has)
    :return: the data written to ``screen.json``
    """
    root = Path(root)
    suite = screen_tasks(tasks)
    target = Path(report_dir) if report_dir is not None else root / "report"
    target.mkdir(parents=True, exist_ok=True)
    order, labels, cells = collect_screen(root, suite, models, seeds)
    if not order:
        raise FileNotFoundError(f"No runs of the screen's tasks in {root} (expected {root}/<env_id>/<model>/seed_<n>)")
    if improvement_over is None:
        improvement_over = [model for model in IMPROVEMENT_OVER if model in order]
    elif not improvement_over or any(model not in order for model in improvement_over):
        raise ValueError(
            f"improvement_over must name one or more of the reported models {order}, got {list(improvement_over)} "
            "(a model left out of --models is not reported)"
        )
    randoms = random_scores([task.env_id for task in suite], [root, target], target, episodes=random_episodes)
    references = {}
    for env_id, cell in cells.get(SCREEN_REFERENCE, {}).items():
        scores = [*cell.scores.values(), *cell.others.values()]  # every run of the reference, whatever --seeds
        if scores:
            references[env_id] = {"mean": float(np.mean(scores)), "runs": len(scores), "complete": cell.complete}
    screen = Screen(root, suite, order, labels, cells, randoms, references)
    aggregate, matrices = aggregate_screen(screen, partial, reps, improvement_over)
    figures = _figures(target, screen, aggregate, matrices, reps) + _curve_figure(target, screen, max(1, reps // 20))
    data = {
        "root": str(root),
        "tasks": [dataclasses.asdict(task) for task in suite],
        "protocol": {"eval_freq": SCREEN_EVAL_FREQ, "eval_episodes": SCREEN_EVAL_EPISODES},
        "reference": SCREEN_REFERENCE,
        "partial": partial,
        "improvement_over": list(improvement_over),
        "random": {env_id: {k: v for k, v in value.items() if k != "returns"} for env_id, value in randoms.items()},
        "references": references,
        "models": order,
        "labels": labels,
        "runs": {
            model: {
                env_id: {
                    "expected": cell.expected,
                    "scores": {str(seed): score for seed, score in sorted(cell.scores.items())},
                    "normalised": {str(seed): screen.normalise(env_id, score) for seed, score in sorted(cell.scores.items())},
                    "complete": cell.complete,
                    "missing": {str(seed): note for seed, note in sorted(cell.notes.items())},
                }
                for env_id, cell in cells[model].items()
            }
            for model in order
        },
        "aggregate": aggregate,
        "reps": reps,
        "files": [REPORT_FILE, DATA_FILE, *figures],
        "report_dir": str(target),
    }
    text = "\n".join(
        [
            *_intro(screen),
            *_aggregate_lines(screen, aggregate, partial, reps, improvement_over),
            *_task_lines(screen),
            *_missing_lines(screen),
        ]
    )
    (target / REPORT_FILE).write_text(text + "\n")
    (target / DATA_FILE).write_text(json.dumps(data, indent=2))
    return data


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def _estimate(entry: dict[str, float]) -> str:
    return f"{entry['value']:.2f} [{entry['low']:.2f}, {entry['high']:.2f}]"


def _seeds_text(seeds: Sequence[int]) -> str:
    """``0, 1, 2, 4`` as ``0-2, 4``."""
    ranges: list[list[int]] = []
    for seed in sorted(seeds):
        if ranges and ranges[-1][-1] == seed - 1:
            ranges[-1].append(seed)
        else:
            ranges.append([seed])
    return ", ".join(str(r[0]) if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in ranges)


def _reference_label(screen: Screen) -> str:
    return screen.labels.get(SCREEN_REFERENCE, SCREEN_REFERENCE)


def _intro(screen: Screen) -> list[str]:
    reference = _reference_label(screen)
    return [
        f"# Screen: `{screen.root}`",
        "",
        f"{len(screen.tasks)} tasks; a run's score is its deterministic evaluation ({SCREEN_EVAL_EPISODES} episodes) at "
        f"the task's budget; normalised per task: (score - random) / ({reference} - random), where random is a uniform "
        f"random policy's mean return and {reference} the mean score of its runs on the task.",
        "",
    ]


def _aggregate_lines(
    screen: Screen, aggregate: dict[str, Any], partial: bool, reps: int, improvement_over: Sequence[str]
) -> list[str]:
    """The aggregate's table and its notes."""
    over = list(improvement_over)
    lines = ["## Aggregate: normalised scores over tasks (rliable)", ""]
    if not aggregate and partial:
        lines.append(f"No model has every seed on a task where {_reference_label(screen)} has runs yet.")
    elif not aggregate:
        lines.append(
            "No model is complete on every task yet (`screen report --partial` aggregates each model over the tasks it "
            "has complete)."
        )
    else:
        header = "| Model | Tasks | Runs | IQM [95% CI] | Mean [95% CI] | "
        lines += [header + "".join(f"P(> {screen.labels[o]}) [95% CI] | " for o in over) + "Worst task |"]
        lines += ["|---" * (6 + len(over)) + "|"]
        for model, entry in aggregate.items():
            row = [entry["label"] + ("" if entry["complete"] else f" {PARTIAL_MARK}"), f"{len(entry['tasks'])}/"
                   f"{len(screen.tasks)}", str(entry["runs"]), _estimate(entry["iqm"]), _estimate(entry["mean"])]  # fmt: skip
            for other in over:
                found = entry["probability_of_improvement"].get(other)
                fewer = (
                    "" if found is None or len(found["tasks"]) == len(entry["tasks"]) else f" ({len(found['tasks'])} tasks)"
                )
                row.append("(itself)" if other == model else "-" if found is None else _estimate(found) + fewer)
            row.append(f"{_fmt(entry['worst_task']['normalised'])} ({entry['worst_task']['env_id']})")
            lines.append("| " + " | ".join(row) + " |")
        lines += [
            "",
            "- IQM and Mean over all (run, task) normalised scores; [95% CI]: stratified bootstrap over runs within each "
            f"task ({reps} resamples). P(> Y): the probability that a run of the model scores higher than a run of Y on a "
            "task, averaged over the tasks both have complete. Worst task: the lowest mean normalised score of a task.",
        ]
        if any(not entry["complete"] for entry in aggregate.values()):
            lines.append(
                f"- {PARTIAL_MARK} Partial: over the tasks where the model has every seed (and {_reference_label(screen)} "
                "has runs); not comparable with a model over all tasks."
            )
    left_out = [model for model in screen.models if model not in aggregate]
    if left_out:
        lines += ["", "Not in the aggregate: " + ", ".join(f"`{model}`" for model in left_out) + " (see Missing)."]
    return [*lines, ""]


def _task_lines(screen: Screen) -> list[str]:
    """The normalised score per task, then one table per task."""
    lines = ["## Normalised score per task (mean over runs)", ""]
    lines += ["| Model | " + " | ".join(screen.env_ids) + " |", "|---" * (len(screen.tasks) + 1) + "|"]
    for model in screen.models:
        row = [screen.labels[model]]
        for env_id in screen.env_ids:
            cell = screen.cells[model][env_id]
            incomplete = f" ({len(cell.scores)}/{len(cell.expected)})" if cell.scores and not cell.complete else ""
            row.append(_fmt(screen.mean_normalised(model, env_id)) + incomplete)
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "(k/n): k of the model's n seeds scored so far; -: none yet, or no reference on the task.", ""]
    lines += ["## Per task", "", "Mean ± std (ddof=0) of the runs' final scores; Normalised: of that mean.", ""]
    for task in screen.tasks:
        random, reference = screen.random[task.env_id], screen.references.get(task.env_id)
        ref_text = "none yet"
        if reference is not None:
            runs = f"{reference['runs']} run{'s' if reference['runs'] > 1 else ''}"
            ref_text = f"{reference['mean']:.1f} ({runs}{'' if reference['complete'] else ', incomplete'})"
            if screen.unusable(task.env_id):
                ref_text += ", no better than the random policy: this task normalises nothing at this budget"
        lines += [
            f"### {task.env_id} ({task.timesteps} steps, warm-up {task.learning_starts})",
            "",
            f"Random policy: {random['mean']:.1f} ± {random['std']:.1f} ({random['episodes']} episodes, seed "
            f"{random['seed']}); {_reference_label(screen)}: {ref_text}.",
            "",
            "| Model | Runs | Mean ± std | Final per seed | Normalised |",
            "|---|---|---|---|---|",
        ]
        for model in screen.models:
            cell = screen.cells[model][task.env_id]
            values = np.array(list(cell.scores.values()))
            if not values.size:
                lines.append(f"| {screen.labels[model]} | 0/{len(cell.expected)} | - | - | - |")
                continue
            finals = ", ".join(f"{seed}: {score:.1f}" for seed, score in sorted(cell.scores.items()))
            lines.append(
                f"| {screen.labels[model]} | {values.size}/{len(cell.expected)} | {values.mean():.1f} ± {values.std():.1f} | "
                f"{finals} | {_fmt(screen.mean_normalised(model, task.env_id))} |"
            )
        lines.append("")
    return lines


def _missing_lines(screen: Screen) -> list[str]:
    """What each model lacks, per task and seed."""
    lines = ["## Missing", ""]
    for model in screen.models:
        for env_id, cell in screen.cells[model].items():
            if cell.complete:
                continue
            by_note: dict[str, list[int]] = {}
            for seed, note in sorted(cell.notes.items()):
                by_note.setdefault(note, []).append(seed)
            parts = [f"seed{'s' if len(seeds) > 1 else ''} {_seeds_text(seeds)}: {note}" for note, seeds in by_note.items()]
            lines.append(f"- `{model}` on {env_id}: " + "; ".join(parts))
    for env_id in screen.env_ids:
        if screen.unusable(env_id):
            lines.append(
                f"- {env_id}: the reference ({_reference_label(screen)}, {screen.references[env_id]['mean']:.1f}) does no "
                f"better than the random policy ({screen.random[env_id]['mean']:.1f}): no normalised score, no aggregate"
            )
    if len(lines) == 2:
        lines.append("Nothing: every model has a score for every seed on every task.")
    return lines


def _figures(target: Path, screen: Screen, aggregate: dict[str, Any], matrices: dict[str, np.ndarray], reps: int) -> list[str]:
    """The aggregate's figures, each with the JSON behind it next to it; none without a model in the aggregate."""
    if not aggregate:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from rliable import plot_utils

    models = list(aggregate)
    names = {
        model: aggregate[model]["label"] + ("" if aggregate[model]["complete"] else f" {PARTIAL_MARK}") for model in models
    }
    partial = any(not aggregate[model]["complete"] for model in models)
    suffix = f"\n{PARTIAL_MARK}: partial, over the tasks it has complete" if partial else ""

    # IQM and mean with their intervals
    statistics = ("iqm", "mean")
    points = {names[m]: np.array([aggregate[m][k]["value"] for k in statistics]) for m in models}
    bounds = {names[m]: np.array([[aggregate[m][k][end] for k in statistics] for end in ("low", "high")]) for m in models}
    height = 0.6 * len(models)  # inches (rliable's figure: row_height per model); the texts are placed in inches
    fig, _ = plot_utils.plot_interval_estimates(
        points, bounds, metric_names=["IQM", "Mean"], algorithms=[names[m] for m in models], xlabel="Normalised score",
        subfigure_width=4.0, row_height=0.6, xlabel_y_coordinate=-0.6 / height,
    )  # fmt: skip
    fig.suptitle("Aggregate normalised score (95% stratified-bootstrap CI)" + suffix, y=1 + (0.75 + 0.25 * partial) / height)
    fig.savefig(target / "aggregate.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    _write(
        target / "aggregate.json", {m: {k: aggregate[m][k] for k in ("label", "tasks", "runs", *statistics)} for m in models}
    )
    files = ["aggregate.png", "aggregate.json"]

    # probabilities of improvement
    pairs = {
        f"{names[m]},{screen.labels[other]}": found
        for m in models
        for other, found in aggregate[m]["probability_of_improvement"].items()
    }
    if pairs:
        fig, ax = plt.subplots(figsize=(4.5, 0.8 + 0.45 * len(pairs)))
        plot_utils.plot_probability_of_improvement(
            {pair: found["value"] for pair, found in pairs.items()},
            {pair: np.array([found["low"], found["high"]]) for pair, found in pairs.items()},
            ax=ax,
        )
        ax.set_title("Probability of improvement (95% CI)" + suffix, fontsize="medium")
        fig.savefig(target / "improvement.png", dpi=110, bbox_inches="tight")
        plt.close(fig)
        _write(target / "improvement.json", pairs)
        files += ["improvement.png", "improvement.json"]

    # performance profiles
    values = np.concatenate([matrix.ravel() for matrix in matrices.values()])
    taus = np.linspace(min(0.0, float(values.min())), max(1.0, float(values.max())), 101)
    profiles, bands = evaluation.performance_profiles({names[m]: matrices[m] for m in models}, taus, reps=max(1, reps // 5))
    fig, ax = plt.subplots(figsize=(7, 4.5))
    colours = {names[m]: f"C{index % 10}" for index, m in enumerate(models)}
    plot_utils.plot_performance_profiles(
        profiles, taus, performance_profile_cis=bands, ax=ax, colors=colours, xlabel=r"Normalised score $\tau$"
    )
    ax.axvline(1.0, color="0.5", ls="--", lw=0.8)
    handles = [Line2D([], [], color=colour, lw=2) for colour in colours.values()]
    ax.legend(handles, list(colours), fontsize="small", loc="upper right")
    ax.set_title("Performance profiles (95% stratified-bootstrap bands)" + suffix, fontsize="medium")
    fig.savefig(target / "performance_profiles.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    curves = {
        m: {
            "label": names[m],
            "tasks": aggregate[m]["tasks"],
            "fraction": profiles[names[m]].tolist(),
            "low": bands[names[m]][0].tolist(),
            "high": bands[names[m]][1].tolist(),
        }
        for m in models
    }
    _write(target / "performance_profiles.json", {"tau": taus.tolist(), "models": curves})
    return [*files, "performance_profiles.png", "performance_profiles.json"]


def learning_curves(screen: Screen, reps: int) -> dict[str, list[tuple[str, list[int], list[tuple[float, float, float]]]]]:
    """
    :param screen: the screen
    :param reps: bootstrap resamples per evaluation step
    :return: env id -> per model with scored runs there, ``(label, steps, [(IQM, low, high) per step])``: the IQM over
        its scored runs of their evaluation returns, at the evaluation steps they all have
    """
    curves = {}
    for env_id in screen.env_ids:
        rows = []
        for model in screen.models:
            runs = [evaluation.read_run(run_dir) for run_dir in screen.cells[model][env_id].run_dirs.values()]
            steps = evaluation.common_steps(runs)
            if steps:
                estimates = evaluation.iqm_curve(runs, steps, reps=reps)
                rows.append((screen.labels[model], steps, [(e.value, e.low, e.high) for e in estimates]))
        if rows:
            curves[env_id] = rows
    return curves


def _curve_figure(target: Path, screen: Screen, reps: int) -> list[str]:
    """Each task's learning curves (``curves.png``, a panel per task) and the JSON behind them; none without a score."""
    curves = learning_curves(screen, reps)
    if not curves:
        return []
    from sb3_soup.experiments.plots import plot_evaluations

    plot_evaluations(curves, target / "curves.png", columns=4, references={e: screen.random[e]["mean"] for e in curves})
    data = {
        env_id: {
            "random": screen.random[env_id]["mean"],
            "models": [
                {"label": label, "steps": steps, **dict(zip(("iqm", "low", "high"), map(list, zip(*estimates)), strict=True))}
                for label, steps, estimates in rows
            ],
        }
        for env_id, rows in curves.items()
    }
    _write(target / "curves.json", data)
    return ["curves.png", "curves.json"]


def _write(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=2))
