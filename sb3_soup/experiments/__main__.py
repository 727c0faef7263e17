"""
Command line of the experiment runner.

    python -m sb3_soup.experiments run --suite models --env Hopper-v4 --timesteps 100000 --seeds 3 --out runs/hopper
    python -m sb3_soup.experiments run --suite confidence --env Hopper-v4 --timesteps 100000 --seeds 3 --out runs/hopper
    python -m sb3_soup.experiments run --suite benchmark --env Hopper-v4 --timesteps 200000 --out runs/benchmark-Hopper-v4
    python -m sb3_soup.experiments report runs/hopper
    python -m sb3_soup.experiments report runs/hopper --suite confidence
    python -m sb3_soup.experiments trap runs/hopper --suite models
    python -m sb3_soup.experiments screen run --root runs/screen --models td3_zoo,ddpg_zoo,sac_zoo,soup_defaults
    python -m sb3_soup.experiments screen run --root runs/screen --name soup_mask1_k10 --seeds 3 \
        --hyperparams mask_prob=1.0 n_heads=10
    python -m sb3_soup.experiments screen report runs/screen --partial --to runs/screen-report

Suites run into the same folder share the runs they have in common (the confidence suite's ``none`` and ``adaptive``
are the models suite's ``dbddpg`` and ``soup``): the second command trains only the runs that are new. The screening
suite (``screen``) trains models on a fixed list of tasks (:data:`~sb3_soup.experiments.grid.SCREEN_TASKS`), one
experiment folder per task under its root, and reports their scores normalised between a random policy and TD3.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sb3_soup.experiments.grid import (
    SCREEN_BASELINES,
    SCREEN_SEEDS,
    SCREEN_TASKS,
    SUITES,
    VARIANTS,
    build_grid,
    build_screen,
    parse_overrides,
    parse_seeds,
    read_candidates,
)


def _csv(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


def _ints(text: str) -> list[int]:
    return [int(part) for part in _csv(text)]


def _seeds(text: str) -> list[int]:
    """``parse_seeds`` for argparse, which shows an ``ArgumentTypeError``'s message (a ``ValueError``'s it replaces)."""
    try:
        return parse_seeds(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from error


def _count(text: str) -> int:
    """A whole number >= 1, for argparse (which shows the message)."""
    if not text.strip().isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return int(text)


def make_parser() -> argparse.ArgumentParser:
    """:return: the parser of ``run``, ``report``, ``trap`` and ``screen``"""
    parser = argparse.ArgumentParser(
        prog="python -m sb3_soup.experiments", description="Reproduce the SOUP paper's comparisons."
    )
    commands = parser.add_subparsers(dest="command", required=True)

    run = commands.add_parser("run", help="train every (model, seed) run of a suite; resumable")
    run.add_argument("--env", required=True, help="Gymnasium env id, e.g. Hopper-v4")
    run.add_argument("--suite", default="models", choices=sorted(SUITES), help="which comparison (default: models)")
    run.add_argument("--models", type=_csv, help=f"narrow the suite to these, comma-separated (known: {', '.join(VARIANTS)})")
    run.add_argument("--heads", type=_ints, help="head counts K, comma-separated (default: the suite's)")
    run.add_argument(
        "--name",
        help="store the runs as this model (folder and column title), e.g. for ablations: several --hyperparams settings "
        "of one model side by side in one --out folder (needs exactly one of --models)",
    )
    run.add_argument(
        "--seeds",
        type=_seeds,
        help="a count (3 -> 0,1,2) or a list (1,5), for every model (default: 3 each; the benchmark suite: 5 for "
        "soup_defaults and td3_zoo)",
    )
    run.add_argument("--timesteps", type=int, help="steps per run (default: n_timesteps from soup.yml, else 100000)")
    run.add_argument("--out", required=True, help="experiment folder")
    run.add_argument(
        "--eval-freq",
        type=int,
        default=10_000,
        help="evaluate the deterministic policy every N steps, as SB3's EvalCallback (0: never; default: 10000)",
    )
    run.add_argument("--eval-episodes", type=int, default=10, help="episodes per evaluation (default: 10)")
    _add_training_options(
        run,
        hyperparams_file="RL-Zoo style YAML for SOUP's models (default: hyperparams/soup_paper.yml for the paper's, "
        "soup.yml for soup_defaults)",
        ray_address="run as tasks on this Ray cluster ('auto', 'host:port', 'ray://host:10001', or 'local' for a private "
        "one); --out must be on a filesystem shared by its nodes",
    )

    report = commands.add_parser("report", help="Table 1 metrics, learning curves and confidence plots of a folder")
    report.add_argument("out", help="experiment folder")
    report.add_argument(
        "--suite",
        choices=sorted(SUITES),
        help="report one suite's models, with its column titles and baseline, into OUT/report-SUITE (default: all models)",
    )
    report.add_argument(
        "--partial",
        action="store_true",
        help="also use the episodes of unfinished runs so far (marked); default: finished only",
    )
    report.add_argument("--threshold", type=float, help="Episode threshold for every env (default: paper's, if any)")
    report.add_argument("--speedup-threshold", type=float, help="Speed Up running-average threshold for every env")
    report.add_argument("--window", type=int, default=100, help="running-average window in episodes (0: cumulative mean)")
    report.add_argument(
        "--baseline",
        help="model id or suite variant Speed Up compares to (default: the suite's: ddpg, or none for confidence)",
    )
    report.add_argument(
        "--x", dest="x_axis", default="both", choices=["episodes", "timesteps", "both"], help="curves' x-axis (default: both)"
    )
    report.add_argument("--to", dest="report_dir", help="write the report files here (default: OUT, or OUT/report-SUITE)")
    report.add_argument("--eval-step", type=int, help="evaluation step of evaluation.md (default: the last one every run has)")
    report.add_argument(
        "--eval-last",
        type=_count,
        default=1,
        metavar="N",
        help="evaluation.md scores a run by the mean of its last N evaluations up to the step, e.g. 6 at 200k steps with "
        "an evaluation every 10k: 150k-200k (default: 1, the step's alone)",
    )
    report.add_argument(
        "--reps", type=int, default=10_000, help="bootstrap resamples of evaluation.md's intervals (default: 10000)"
    )
    report.add_argument(
        "--with",
        dest="extra",
        action="append",
        default=[],
        metavar="FOLDER",
        help="another experiment folder whose runs join the report (e.g. baselines trained longer, with --eval-step)",
    )

    trap = commands.add_parser(
        "trap", help="steps each finished run spent in a short-fall trap, and its final actions' saturation"
    )
    trap.add_argument("out", help="experiment folder")
    trap.add_argument("--suite", choices=sorted(SUITES), help="one suite's models, written to OUT/report-SUITE")
    trap.add_argument(
        "--lengths",
        type=_length_range,
        default=(21, 24),
        help="episode lengths of the trap, SHORTEST-LONGEST (default: 21-24, Hopper's saturated-action fall)",
    )
    trap.add_argument("--window", type=int, default=1000, help="window in steps (default: 1000)")
    trap.add_argument("--fraction", type=float, default=0.9, help="trapped: more than this fraction of a window's episodes")
    trap.add_argument("--eval-episodes", type=int, default=3, help="deterministic episodes for saturation (0: skip)")
    trap.add_argument(
        "--final-fraction", type=float, default=0.2, help="the last part of each run whose mean return is shown (default: 0.2)"
    )
    trap.add_argument("--to", dest="report_dir", help="write trap.md and trap.json here (default: OUT, or OUT/report-SUITE)")
    _add_screen_parser(commands)
    return parser


def _add_training_options(parser: argparse.ArgumentParser, hyperparams_file: str, ray_address: str) -> None:
    """The options of ``run`` and ``screen run`` on how runs train (:func:`_run_options` passes them on)."""
    parser.add_argument("--hyperparams", nargs="*", default=[], metavar="[MODEL:]KEY=VALUE", help="override hyper-parameters")
    parser.add_argument("--hyperparams-file", help=hyperparams_file)
    parser.add_argument("--workers", type=int, help="parallel runs (default: number of cores available)")
    parser.add_argument("--checkpoint-freq", type=int, default=10_000, help="checkpoint every N steps (0: only at stops)")
    parser.add_argument("--stop-after", type=int, help="stop each run after N new steps (resumable), e.g. for time slices")
    parser.add_argument("--ray-address", help=ray_address)
    parser.add_argument("--no-progress", action="store_true", help="no progress bars or progress lines")


def _add_screen_parser(commands: Any) -> None:
    """``screen run``, ``screen report`` and ``screen tasks``."""
    tasks = ", ".join(task.env_id for task in SCREEN_TASKS)
    screen = commands.add_parser(
        "screen",
        help="the screening suite: models on a fixed task list, scores normalised between random (0) and TD3 (1)",
        description=f"The screening suite's tasks: {tasks} (budgets and warm-ups: `screen tasks`).",
    )
    actions = screen.add_subparsers(dest="screen_command", required=True)

    run = actions.add_parser("run", help="train models on every task of the suite; resumable (runs already done are reused)")
    run.add_argument("--root", required=True, help="the screen's folder: one experiment folder per task, ROOT/ENV")
    run.add_argument(
        "--models",
        type=_csv,
        help=f"variants, comma-separated (default: soup_defaults; the baselines: {','.join(SCREEN_BASELINES)})",
    )
    run.add_argument(
        "--name",
        help="store the runs as this model: a candidate, one named setting of one variant (default soup_defaults) given "
        "by --hyperparams",
    )
    run.add_argument(
        "--candidates",
        help="a YAML file of SOUP's candidates (name: settings, e.g. docs/results/screen/candidates.yml): each runs as "
        "--name NAME with its settings, one candidate after the other, instead of --models/--name",
    )
    run.add_argument("--only", type=_csv, help="with --candidates: these candidates only, comma-separated, in this order")
    run.add_argument(
        "--seeds", type=_seeds, default=list(range(SCREEN_SEEDS)), help=f"a count or a list (default: {SCREEN_SEEDS})"
    )
    run.add_argument("--tasks", type=_csv, help="narrow the suite to these env ids, comma-separated")
    _add_training_options(
        run,
        hyperparams_file="RL-Zoo style YAML for SOUP's models (default: hyperparams/soup.yml)",
        ray_address="run as tasks on this Ray cluster (see `run --help`)",
    )

    report = actions.add_parser("report", help="normalised scores per task and aggregated with rliable")
    report.add_argument("root", help="the screen's folder (only read)")
    report.add_argument("--to", dest="report_dir", help="write the report files here (default: ROOT/report)")
    report.add_argument(
        "--partial",
        action="store_true",
        help="aggregate every model over the tasks it has complete (marked); default: only models complete on all tasks",
    )
    report.add_argument("--tasks", type=_csv, help="narrow the suite to these env ids, comma-separated")
    report.add_argument("--models", type=_csv, help="report these models only (folder names), comma-separated")
    report.add_argument(
        "--seeds", type=_seeds, help="the seeds every model should have (default: per model, those it has on any task)"
    )
    report.add_argument("--reps", type=int, default=10_000, help="bootstrap resamples of the intervals (default: 10000)")
    report.add_argument(
        "--improvement-over",
        type=_csv,
        help="the models each model's probability of improvement is over, comma-separated, among those reported "
        "(default: td3_zoo,ddpg_zoo, those present; e.g. soup_defaults to weigh a candidate against the defaults)",
    )

    actions.add_parser("tasks", help="the suite's tasks, budgets and warm-ups")


def _length_range(text: str) -> tuple[int, int]:
    parts = text.split("-")
    if len(parts) != 2 or not all(part.strip().isdigit() for part in parts):
        raise argparse.ArgumentTypeError(f"expected SHORTEST-LONGEST episode lengths such as 21-24, got {text!r}")
    return int(parts[0]), int(parts[1])


def run_specs(args: argparse.Namespace) -> list[Any]:
    """
    :param args: parsed ``run`` arguments
    :return: the runs they ask for
    """
    return build_grid(
        args.env,
        args.out,
        suite=args.suite,
        models=args.models,
        heads=args.heads,
        seeds=args.seeds,
        timesteps=args.timesteps,
        eval_freq=args.eval_freq,
        eval_episodes=args.eval_episodes,
        **_run_options(args),
    )


def _run_options(args: argparse.Namespace) -> dict[str, Any]:
    """:return: the options ``run`` and ``screen run`` share, as the keyword arguments of their grid builders"""
    return dict(
        overrides=parse_overrides(args.hyperparams),
        name=args.name,
        hyperparams_file=args.hyperparams_file,
        checkpoint_freq=args.checkpoint_freq,
        stop_after=args.stop_after,
    )


def run_command(args: argparse.Namespace) -> int:
    """
    :param args: parsed ``run`` arguments
    :return: exit status: 0 when every run finished, 1 when some failed, 2 when some are not finished yet
        (interrupted, or busy: being trained by another ``run`` command)
    """
    from sb3_soup.experiments.parallel import run_grid
    from sb3_soup.experiments.report import write_grid

    specs = run_specs(args)
    write_grid(args.out, specs, args.suite, args.heads)
    print(f"{len(specs)} runs of {specs[0].timesteps} steps -> {args.out}", file=sys.stderr)
    results = run_grid(specs, args.workers, progress=not args.no_progress, ray_address=args.ray_address or None)
    return _summarise(results)


def _summarise(results: Sequence[dict[str, Any]]) -> int:
    """
    Print a grid's results.

    :param results: :func:`~sb3_soup.experiments.parallel.run_grid`'s
    :return: the exit status of ``run``
    """
    counts = Counter(result["status"] for result in results)
    print("Summary: " + ", ".join(f"{count} {status}" for status, count in sorted(counts.items())))
    for result in results:
        if result["status"] == "failed":
            print(f"  FAILED {result['key']}: {result.get('error')} (see {result['run_dir']}/error.json)")
        elif result["status"] == "interrupted":
            print(f"  interrupted {result['key']} at step {result['step']}: re-run the same command to resume")
        elif result["status"] == "busy":
            print(f"  busy {result['key']}: {result.get('error')}; re-run the command once that one is done")
    if counts.get("failed"):
        return 1
    return 2 if counts.get("interrupted") or counts.get("busy") else 0


def report_command(args: argparse.Namespace) -> int:
    """
    :param args: parsed ``report`` arguments
    :return: exit status
    """
    from sb3_soup.experiments.report import collect_runs, make_report

    thresholds = None
    if args.threshold is not None or args.speedup_threshold is not None:
        # The same thresholds for every env of the folder (the paper's fill in the one not given).
        from sb3_soup.experiments.metrics import paper_thresholds

        envs = {record.spec.env_id for record in collect_runs(args.out)}
        thresholds = {}
        for env_id in envs:
            episode, lower = paper_thresholds(env_id)
            thresholds[env_id] = (
                args.threshold if args.threshold is not None else episode,
                args.speedup_threshold if args.speedup_threshold is not None else lower,
            )
    data = make_report(
        args.out,
        thresholds,
        window=args.window or None,
        baseline=args.baseline,
        x_axis=args.x_axis,
        suite=args.suite,
        partial=args.partial,
        report_dir=args.report_dir,
        eval_step=args.eval_step,
        eval_last=args.eval_last,
        extra=args.extra,
        bootstrap_reps=args.reps,
    )
    print((Path(data["report_dir"]) / "table.md").read_text())
    if "evaluation.md" in data["files"]:
        print((Path(data["report_dir"]) / "evaluation.md").read_text())
    print("Wrote " + ", ".join(data["files"]) + f" in {data['report_dir']}")
    return 0


def trap_command(args: argparse.Namespace) -> int:
    """
    :param args: parsed ``trap`` arguments
    :return: exit status
    """
    from sb3_soup.experiments.trap import trap_report

    table, _, _ = trap_report(
        args.out,
        suite=args.suite,
        window=args.window,
        trap_lengths=args.lengths,
        fraction=args.fraction,
        eval_episodes=args.eval_episodes,
        report_dir=args.report_dir,
        final_fraction=args.final_fraction,
    )
    print(table)
    return 0


def screen_specs(args: argparse.Namespace) -> list[Any]:
    """
    :param args: parsed ``screen run`` arguments
    :return: the runs they ask for
    """
    options = _run_options(args)
    if not args.candidates:
        if args.only:
            raise ValueError("--only chooses among --candidates: pass a candidates file")
        return build_screen(args.root, models=args.models, seeds=args.seeds, tasks=args.tasks, **options)
    if args.models or args.name:
        raise ValueError("--candidates runs each candidate as a named SOUP model: drop --models and --name")
    specs = []
    for name, settings in read_candidates(args.candidates, args.only).items():
        # the candidate's settings for SOUP's defaults, then --hyperparams' (for every candidate)
        overrides = {**options["overrides"], "*": {**settings, **options["overrides"].get("*", {})}}
        specs += build_screen(
            args.root, seeds=args.seeds, tasks=args.tasks, **dict(options, overrides=overrides, name=name)
        )  # fmt: skip
    return specs


def screen_command(args: argparse.Namespace) -> int:
    """
    :param args: parsed ``screen`` arguments
    :return: exit status (``screen run``: as ``run``'s)
    """
    from sb3_soup.experiments.grid import SCREEN_SUITE, screen_tasks

    if args.screen_command == "tasks":
        print("| Task | Budget (steps) | Warm-up (learning_starts) |\n|---|---|---|")
        for task in SCREEN_TASKS:
            print(f"| {task.env_id} | {task.timesteps} | {task.learning_starts} |")
        return 0
    if args.screen_command == "report":
        from sb3_soup.experiments.screen import REPORT_FILE, screen_report

        data = screen_report(
            args.root, args.report_dir, tasks=args.tasks, models=args.models, seeds=args.seeds, partial=args.partial,
            reps=args.reps, improvement_over=args.improvement_over,
        )  # fmt: skip
        print((Path(data["report_dir"]) / REPORT_FILE).read_text())
        print("Wrote " + ", ".join(data["files"]) + f" in {data['report_dir']}")
        return 0

    from sb3_soup.experiments.parallel import run_grid
    from sb3_soup.experiments.report import write_grid
    from sb3_soup.experiments.screen import random_scores

    specs = screen_specs(args)
    tasks = screen_tasks(args.tasks)
    for task in tasks:
        write_grid(Path(args.root) / task.env_id, [spec for spec in specs if spec.env_id == task.env_id], SCREEN_SUITE)
    random_scores([task.env_id for task in tasks], [args.root], args.root)  # the report's 0, computed once
    models = sorted({spec.model for spec in specs})
    print(f"{len(specs)} runs ({', '.join(models)} on {len(tasks)} tasks) -> {args.root}", file=sys.stderr)
    results = run_grid(specs, args.workers, progress=not args.no_progress, ray_address=args.ray_address or None)
    return _summarise(results)


def main(argv: Sequence[str] | None = None) -> int:
    """
    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: exit status
    """
    args = make_parser().parse_args(argv)
    commands = {"run": run_command, "report": report_command, "trap": trap_command, "screen": screen_command}
    return commands[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
