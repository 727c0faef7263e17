"""
The screening suite (issue 19): its runs (the task table's budgets and warm-ups, shared with the baselines' `run`
commands), the random policy's scores and their cache, and `screen report`'s normalised, rliable-aggregated scores.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sb3_soup.experiments import grid, logs, screen
from sb3_soup.experiments.__main__ import main, make_parser, run_specs, screen_specs
from sb3_soup.experiments.grid import SCREEN_BASELINES, SCREEN_TASKS, build_grid, build_screen, parse_overrides, soup_defaults
from sb3_soup.experiments.report import write_grid
from sb3_soup.experiments.runner import DONE_FILE, STATUS_FILE

REPS = 200  # bootstrap resamples: enough for the checks, fast


# ---------------------------------------------------------------- the runs


def test_the_screen_reuses_the_baselines_runs_started_with_run(tmp_path):
    """Each baseline's screen run is the one `run --suite benchmark ... --hyperparams MODEL:learning_starts=LS` built."""
    root = tmp_path / "screen"
    screen_args = make_parser().parse_args(["screen", "run", "--root", str(root), "--models", ",".join(SCREEN_BASELINES)])
    suite = {(spec.env_id, spec.key): spec for spec in screen_specs(screen_args)}
    assert len(suite) == len(SCREEN_TASKS) * len(SCREEN_BASELINES) * 5
    for task in SCREEN_TASKS:
        for model in SCREEN_BASELINES:
            command = ["run", "--env", task.env_id, "--suite", "benchmark", "--models", model, "--seeds", "5",
                       "--timesteps", str(task.timesteps), "--eval-freq", "5000",
                       "--hyperparams", f"{model}:learning_starts={task.learning_starts}",
                       "--out", str(root / task.env_id), "--workers", "1", "--no-progress"]  # fmt: skip
            args = make_parser().parse_args(command)
            for spec in run_specs(args):
                shared = suite[(spec.env_id, spec.key)]
                assert shared.config() == spec.config() and shared.run_dir == spec.run_dir, (task.env_id, spec.key)
    hopper = suite[("Hopper-v4", "td3_zoo/seed_0")].config()
    assert (hopper["timesteps"], hopper["eval_freq"], hopper["eval_episodes"]) == (50_000, 5_000, 10)
    assert hopper["hyperparams"]["learning_starts"] == 10_000 and hopper["algo"] == "td3"


def test_a_run_finished_on_one_task_does_not_skip_the_same_seed_on_the_others(tmp_path):
    """The runs of a screen share model/seed_N names across tasks: a finished one is that task's alone (a finished
    td3_zoo/seed_0 on one task made run_grid skip td3_zoo/seed_0 on every task)."""
    from sb3_soup.experiments import parallel

    specs = build_screen(tmp_path, models=["td3_zoo"], seeds=[0], tasks=["Pendulum-v1", "Hopper-v4"])
    pendulum, hopper = specs
    assert pendulum.key == hopper.key == "td3_zoo/seed_0" and pendulum.run_id != hopper.run_id
    for spec in specs:
        Path(spec.run_dir).mkdir(parents=True)
        (Path(spec.run_dir) / "spec.json").write_text(spec.to_json())
    (Path(pendulum.run_dir) / DONE_FILE).write_text(json.dumps({"timesteps": pendulum.timesteps}))
    results, todo = parallel._skip_finished(specs)
    assert todo == [hopper] and list(results) == [pendulum.run_id]
    (Path(hopper.run_dir) / DONE_FILE).write_text(json.dumps({"timesteps": hopper.timesteps}))
    assert [result["run_dir"] for result in parallel.run_grid(specs, progress=False)] == [pendulum.run_dir, hopper.run_dir]


def test_every_model_trains_a_task_with_its_budget_and_warm_up(tmp_path):
    specs = build_screen(tmp_path, models=["soup_defaults", "sac_zoo"], seeds=[0], tasks=["Pendulum-v1", "Walker2d-v4"])
    assert [(spec.env_id, spec.model) for spec in specs] == [
        ("Pendulum-v1", "soup_defaults"), ("Pendulum-v1", "sac_zoo"), ("Walker2d-v4", "soup_defaults"),
        ("Walker2d-v4", "sac_zoo"),
    ]  # fmt: skip
    assert [(spec.timesteps, spec.hyperparams["learning_starts"]) for spec in specs] == [
        (20_000, 5_000), (20_000, 5_000), (50_000, 10_000), (50_000, 10_000)
    ]  # fmt: skip
    assert all(spec.eval_freq == 5_000 and spec.eval_episodes == 10 for spec in specs)
    assert specs[0].run_dir == str(tmp_path / "Pendulum-v1" / "soup_defaults" / "seed_0")

    # A candidate: SOUP's defaults with a named setting, stored under its name in every task's folder.
    (defaults,) = build_screen(tmp_path, seeds=[0], tasks=["Hopper-v4"])
    (candidate,) = build_screen(
        tmp_path, name="soup_allcritics_d2", seeds=[0], tasks=["Hopper-v4"],
        overrides=parse_overrides(["train_heads=all_critics", "policy_delay=2"]),
    )  # fmt: skip
    assert candidate.model == candidate.label == "soup_allcritics_d2" and candidate.variant == "soup_defaults"
    assert candidate.run_dir == str(tmp_path / "Hopper-v4" / "soup_allcritics_d2" / "seed_0")
    assert candidate.hyperparams == {**defaults.hyperparams, "train_heads": "all_critics", "policy_delay": 2}
    assert (
        defaults.hyperparams["learning_starts"] == 10_000
        and defaults.hyperparams.items()
        >= {key: value for key, value in soup_defaults().items() if key != "learning_starts"}.items()
    )

    with pytest.raises(ValueError, match="fixes learning_starts"):
        build_screen(tmp_path, overrides=parse_overrides(["learning_starts=100"]))
    with pytest.raises(ValueError, match="fixes learning_starts"):
        build_screen(tmp_path, models=["td3_zoo"], overrides=parse_overrides(["td3_zoo:learning_starts=100"]))
    with pytest.raises(ValueError, match="Unknown screen task"):
        build_screen(tmp_path, tasks=["CartPole-v1"])


# ---------------------------------------------------------------- the random policy


def test_the_random_policy_score_is_reproducible():
    first = screen.random_policy_score("Pendulum-v1", episodes=2, seed=3)
    assert first == screen.random_policy_score("Pendulum-v1", episodes=2, seed=3)
    assert len(first["returns"]) == 2 and first["mean"] == pytest.approx(np.mean(first["returns"])) and first["mean"] < 0
    assert screen.random_policy_score("Pendulum-v1", episodes=2, seed=4)["returns"] != first["returns"]


def test_random_scores_are_computed_once_and_cached(tmp_path, monkeypatch):
    computed = []

    def fake_score(env_id, episodes, seed):
        computed.append(env_id)
        return {"mean": -1.0, "std": 0.0, "episodes": episodes, "seed": seed, "returns": [-1.0]}

    monkeypatch.setattr(screen, "random_policy_score", fake_score)
    root, report = tmp_path / "root", tmp_path / "report"
    root.mkdir()
    # the root's cache has Pendulum with the protocol's episodes and seed, and Hopper with others (not used)
    cached = {"Pendulum-v1": {"mean": -1200.0, "episodes": screen.RANDOM_EPISODES, "seed": screen.RANDOM_SEED},
              "Hopper-v4": {"mean": 5.0, "episodes": 3, "seed": screen.RANDOM_SEED}}  # fmt: skip
    (root / screen.RANDOM_SCORES_FILE).write_text(json.dumps(cached))
    scores = screen.random_scores(["Pendulum-v1", "Hopper-v4"], [root, report], report)
    assert computed == ["Hopper-v4"] and scores["Pendulum-v1"]["mean"] == -1200.0 and scores["Hopper-v4"]["mean"] == -1.0
    assert json.loads((root / screen.RANDOM_SCORES_FILE).read_text()) == cached  # the root is only read
    assert list(json.loads((report / screen.RANDOM_SCORES_FILE).read_text())) == ["Hopper-v4"]
    screen.random_scores(["Pendulum-v1", "Hopper-v4"], [root, report], report)
    assert computed == ["Hopper-v4"]  # computed once


# ---------------------------------------------------------------- the report on hand-made runs


def _scored_run(spec, final: float | None, status: str = "finished") -> None:
    """A run folder whose evaluations end with ``final`` at the budget (finished), or stop halfway (unfinished)."""
    run_dir = Path(spec.run_dir)
    run_dir.mkdir(parents=True)
    (run_dir / "spec.json").write_text(spec.to_json())
    (run_dir / logs.MONITOR_FILE).write_text('#{"t_start": 0}\nr,l,t\n1.0,10,0.0\n')
    logs.append_evaluation(run_dir, spec.timesteps // 2, [-5000.0, -5000.0], [200, 200])
    if status == "finished":
        logs.append_evaluation(run_dir, spec.timesteps, [final - 1.0, final + 1.0], [200, 200])
        (run_dir / DONE_FILE).write_text(json.dumps({"timesteps": spec.timesteps}))
    step = spec.timesteps if status == "finished" else spec.timesteps // 2
    (run_dir / STATUS_FILE).write_text(json.dumps({"status": status, "step": step, "total": spec.timesteps}))


@pytest.fixture
def hand_made(tmp_path):
    """
    A screen of two tasks, random scores cached: Pendulum-v1 random -1000, Hopper-v4 random 0.

    - td3_zoo (the reference) seeds 0, 1: Pendulum -300, -100 (reference -200: normalised 0.875, 1.125);
      Hopper 900, 1100 (reference 1000: 0.9, 1.1)
    - ddpg_zoo: Pendulum -600, -200 (0.5, 1.0); Hopper 500, 300 (0.5, 0.3)
    - soup_x (a candidate): Pendulum -200, -200 (1.0, 1.0); Hopper seed 0 2000 (2.0), seed 1 interrupted halfway
    - td3_short: trained for 10k steps on Pendulum, not the task's budget
    """
    root = tmp_path / "screen"
    tasks = ["Pendulum-v1", "Hopper-v4"]
    finals = {
        ("Pendulum-v1", "td3_zoo"): [-300, -100], ("Hopper-v4", "td3_zoo"): [900, 1100],
        ("Pendulum-v1", "ddpg_zoo"): [-600, -200], ("Hopper-v4", "ddpg_zoo"): [500, 300],
        ("Pendulum-v1", "soup_x"): [-200, -200], ("Hopper-v4", "soup_x"): [2000, None],
    }  # fmt: skip
    specs = build_screen(root, models=["td3_zoo", "ddpg_zoo"], seeds=[0, 1], tasks=tasks)
    specs += build_screen(root, name="soup_x", seeds=[0, 1], tasks=tasks, overrides=parse_overrides(["train_heads=all"]))
    for env_id in tasks:
        write_grid(root / env_id, [spec for spec in specs if spec.env_id == env_id], "benchmark")
    for spec in specs:
        final = finals[(spec.env_id, spec.model)][spec.seed]
        _scored_run(spec, final, "finished" if final is not None else "interrupted")
    (short,) = build_grid("Pendulum-v1", root / "Pendulum-v1", models=["td3_zoo"], seeds=[0], timesteps=10_000,
                          eval_freq=5_000, name="td3_short")  # fmt: skip
    _scored_run(short, -150)
    randoms = {env_id: {"mean": mean, "std": 0.0, "episodes": screen.RANDOM_EPISODES, "seed": screen.RANDOM_SEED}
               for env_id, mean in (("Pendulum-v1", -1000.0), ("Hopper-v4", 0.0))}  # fmt: skip
    (root / screen.RANDOM_SCORES_FILE).write_text(json.dumps(randoms))
    return root


def _table_row(text: str, first_cell: str) -> list[str]:
    line = next(line for line in text.splitlines() if line.startswith(f"| {first_cell} |"))
    return [cell.strip() for cell in line.strip("|").split("|")]


def test_report_normalises_per_task_and_aggregates_complete_models(hand_made, tmp_path):
    data = screen.screen_report(hand_made, tmp_path / "report", tasks=["Pendulum-v1", "Hopper-v4"], reps=REPS)
    assert data["models"] == ["td3_zoo", "ddpg_zoo", "soup_x", "td3_short"]
    assert data["references"]["Pendulum-v1"] == {"mean": -200.0, "runs": 2, "complete": True}
    runs = data["runs"]
    assert runs["td3_zoo"]["Pendulum-v1"]["normalised"] == {"0": 0.875, "1": 1.125}
    assert runs["ddpg_zoo"]["Hopper-v4"]["normalised"] == {"0": 0.5, "1": 0.3}
    assert runs["soup_x"]["Hopper-v4"]["scores"] == {"0": 2000.0} and not runs["soup_x"]["Hopper-v4"]["complete"]
    assert runs["soup_x"]["Hopper-v4"]["missing"] == {"1": "interrupted at step 25000/50000"}
    assert "off the task's protocol: timesteps 10000 (the task's: 20000)" in runs["td3_short"]["Pendulum-v1"]["missing"]["0"]

    # Only the models complete on both tasks: TD3's normalised scores 0.875, 0.9, 1.1, 1.125 (IQM 1.0), DDPG's 0.5,
    # 1.0, 0.5, 0.3 (IQM 0.5, mean 0.575); P(DDPG > TD3) = (1/4 on Pendulum + 0 on Hopper) / 2.
    aggregate = data["aggregate"]
    assert list(aggregate) == ["td3_zoo", "ddpg_zoo"]
    assert aggregate["td3_zoo"]["iqm"]["value"] == pytest.approx(1.0) and aggregate["td3_zoo"]["mean"]["value"] == 1.0
    ddpg = aggregate["ddpg_zoo"]
    assert ddpg["iqm"]["value"] == pytest.approx(0.5) and ddpg["mean"]["value"] == pytest.approx(0.575)
    assert ddpg["iqm"]["low"] <= 0.5 <= ddpg["iqm"]["high"] and ddpg["runs"] == 4
    assert ddpg["probability_of_improvement"]["td3_zoo"]["value"] == pytest.approx(0.125)
    assert aggregate["td3_zoo"]["probability_of_improvement"]["ddpg_zoo"]["value"] == pytest.approx(0.875)
    assert ddpg["worst_task"] == {"env_id": "Hopper-v4", "normalised": pytest.approx(0.4)}

    text = (tmp_path / "report" / "screen.md").read_text()
    assert _table_row(text, "DDPG (RL Zoo)")[:3] == ["DDPG (RL Zoo)", "2/2", "4"]
    assert _table_row(text, "DDPG (RL Zoo)")[-1] == "0.40 (Hopper-v4)"
    assert "Not in the aggregate: `soup_x`, `td3_short`" in text
    assert "| soup_x | 1.00 | 2.00 (1/2) |" in text  # the normalised score per task
    assert "| soup_x | 1/2 | 2000.0 ± 0.0 | 0: 2000.0 | 2.00 |" in text  # Hopper-v4's table
    assert "Random policy: -1000.0 ± 0.0 (100 episodes, seed 0); TD3 (RL Zoo): -200.0 (2 runs)." in text
    assert "- `soup_x` on Hopper-v4: seed 1: interrupted at step 25000/50000" in text
    for name in ("aggregate", "improvement", "performance_profiles"):  # every figure with the JSON behind it
        assert {f"{name}.png", f"{name}.json"} <= set(data["files"]) and (tmp_path / "report" / f"{name}.png").stat().st_size
    profiles = json.loads((tmp_path / "report" / "performance_profiles.json").read_text())
    at_one = profiles["tau"].index(min(profiles["tau"], key=lambda tau: abs(tau - 1.0)))
    assert profiles["models"]["ddpg_zoo"]["fraction"][at_one] == pytest.approx(0.0)  # no DDPG run above TD3's 1.0
    assert json.loads((tmp_path / "report" / "screen.json").read_text())["aggregate"]["ddpg_zoo"]["runs"] == 4


def test_seeds_narrow_every_models_tables_and_curves_but_the_reference_keeps_every_run(hand_made, tmp_path):
    tasks = ["Pendulum-v1", "Hopper-v4"]
    data = screen.screen_report(hand_made, tmp_path / "report", tasks=tasks, seeds=[0], reps=REPS)
    assert data["references"]["Hopper-v4"] == {"mean": 1000.0, "runs": 2, "complete": True}  # TD3's seeds 0 and 1
    assert data["runs"]["ddpg_zoo"]["Hopper-v4"]["scores"] == {"0": 500.0}  # seed 1 (300) is left out
    # DDPG's seed 0: Pendulum -600 (0.5), Hopper 500 (0.5), in the per-task table as in the aggregate's worst task
    text = (tmp_path / "report" / "screen.md").read_text()
    assert "| DDPG (RL Zoo) | 0.50 | 0.50 |" in text and "| DDPG (RL Zoo) | 1/1 | 500.0 ± 0.0 | 0: 500.0 | 0.50 |" in text
    assert data["aggregate"]["ddpg_zoo"]["worst_task"]["normalised"] == pytest.approx(0.5)
    hopper = {
        model["label"]: model for model in json.loads((tmp_path / "report" / "curves.json").read_text())["Hopper-v4"]["models"]
    }
    assert hopper["DDPG (RL Zoo)"]["iqm"] == [-5000.0, 500.0]


def test_report_draws_each_tasks_learning_curves_from_the_scored_runs(hand_made, tmp_path):
    data = screen.screen_report(hand_made, tmp_path / "report", tasks=["Pendulum-v1", "Hopper-v4"], reps=REPS)
    assert {"curves.png", "curves.json"} <= set(data["files"]) and (tmp_path / "report" / "curves.png").stat().st_size
    curves = json.loads((tmp_path / "report" / "curves.json").read_text())
    assert list(curves) == ["Pendulum-v1", "Hopper-v4"] and curves["Hopper-v4"]["random"] == 0.0
    hopper = {model["label"]: model for model in curves["Hopper-v4"]["models"]}
    assert list(hopper) == ["TD3 (RL Zoo)", "DDPG (RL Zoo)", "soup_x"]  # td3_short trained Pendulum only, off protocol
    # each run evaluated at half the budget (-5000) and at the budget (its final score); soup_x: its one finished run
    assert hopper["soup_x"]["steps"] == [25_000, 50_000] and hopper["soup_x"]["iqm"] == [-5000.0, 2000.0]
    assert hopper["TD3 (RL Zoo)"]["iqm"] == [-5000.0, pytest.approx(1000.0)]
    assert hopper["DDPG (RL Zoo)"]["low"][1] <= 400.0 <= hopper["DDPG (RL Zoo)"]["high"][1]


def test_partial_report_aggregates_a_model_over_the_tasks_it_has_complete(hand_made, tmp_path):
    data = screen.screen_report(hand_made, tmp_path / "partial", tasks=["Pendulum-v1", "Hopper-v4"], partial=True, reps=REPS)
    soup = data["aggregate"]["soup_x"]
    assert soup["tasks"] == ["Pendulum-v1"] and not soup["complete"] and soup["iqm"]["value"] == pytest.approx(1.0)
    # on Pendulum-v1: 1.0, 1.0 against TD3's 0.875, 1.125 (one of two pairs higher) and DDPG's 0.5, 1.0 (one higher, one tie)
    assert soup["probability_of_improvement"]["td3_zoo"]["value"] == pytest.approx(0.5)
    assert soup["probability_of_improvement"]["ddpg_zoo"]["value"] == pytest.approx(0.75)
    assert "td3_short" not in data["aggregate"]
    text = (tmp_path / "partial" / "screen.md").read_text()
    assert _table_row(text, "soup_x †")[:3] == ["soup_x †", "1/2", "2"] and "† Partial" in text


def test_a_candidate_is_weighed_against_the_models_named_by_improvement_over(hand_made, tmp_path):
    tasks = ["Pendulum-v1", "Hopper-v4"]
    data = screen.screen_report(
        hand_made, tmp_path / "report", tasks=tasks, partial=True, improvement_over=["soup_x"], reps=REPS
    )
    assert data["improvement_over"] == ["soup_x"]
    # on Pendulum-v1, soup_x's one complete task: DDPG's 0.5, 1.0 against soup_x's 1.0, 1.0 (none higher, one tie)
    ddpg = data["aggregate"]["ddpg_zoo"]["probability_of_improvement"]
    assert list(ddpg) == ["soup_x"] and ddpg["soup_x"]["value"] == pytest.approx(0.25) and ddpg["soup_x"]["tasks"] == tasks[:1]
    assert data["aggregate"]["soup_x"]["probability_of_improvement"] == {}  # not over itself
    text = (tmp_path / "report" / screen.REPORT_FILE).read_text()
    assert "| P(> soup_x) [95% CI] | Worst task |" in text and "P(> TD3 (RL Zoo))" not in text
    assert _table_row(text, "soup_x †")[5] == "(itself)"
    ddpg_cell = _table_row(text, "DDPG (RL Zoo)")[5]
    assert ddpg_cell.startswith("0.25 [") and ddpg_cell.endswith("(1 tasks)")
    assert set(json.loads((tmp_path / "report" / "improvement.json").read_text())) == {
        "TD3 (RL Zoo),soup_x",
        "DDPG (RL Zoo),soup_x",
    }
    # a model not in the report is refused, naming the reported ones
    with pytest.raises(ValueError, match=r"improvement_over must name one or more of the reported models \['soup_x'\]"):
        screen.screen_report(hand_made, tmp_path / "other", tasks=tasks, models=["soup_x"], improvement_over=["td3_zoo"])


def test_report_on_a_screen_without_a_complete_model(hand_made, tmp_path):
    tasks = ["Pendulum-v1", "Hopper-v4"]
    data = screen.screen_report(hand_made, tmp_path / "report", tasks=tasks, models=["soup_x"], reps=REPS)
    # no aggregate figures; the curves of the runs scored so far
    assert data["aggregate"] == {} and data["files"] == ["screen.md", "screen.json", "curves.png", "curves.json"]
    text = (tmp_path / "report" / "screen.md").read_text()
    assert "No model is complete on every task yet" in text and "TD3 (RL Zoo): none yet." in text
    with pytest.raises(ValueError, match="No runs of"):
        screen.screen_report(hand_made, tmp_path / "report", models=["nope"], reps=REPS)


# ---------------------------------------------------------------- the command line


def test_a_task_whose_reference_does_no_better_than_random_normalises_nothing(hand_made, tmp_path):
    """Hopper's random policy made 1000, TD3's mean: a normalised score would divide by zero (or by a negative)."""
    cache = hand_made / screen.RANDOM_SCORES_FILE
    randoms = json.loads(cache.read_text())
    randoms["Hopper-v4"]["mean"] = 1000.0
    cache.write_text(json.dumps(randoms))
    data = screen.screen_report(hand_made, tmp_path / "report", tasks=["Pendulum-v1", "Hopper-v4"], partial=True, reps=REPS)
    assert data["runs"]["ddpg_zoo"]["Hopper-v4"]["normalised"] == {"0": None, "1": None}
    assert data["runs"]["ddpg_zoo"]["Pendulum-v1"]["normalised"] == {"0": 0.5, "1": 1.0}  # the other task normalises
    assert data["aggregate"]["ddpg_zoo"]["tasks"] == ["Pendulum-v1"]
    text = (tmp_path / "report" / screen.REPORT_FILE).read_text()
    assert "no better than the random policy: this task normalises nothing at this budget" in text
    assert "- Hopper-v4: the reference (TD3 (RL Zoo), 1000.0) does no better than the random policy (1000.0)" in text


def test_screen_command_runs_resumably_and_reports(tmp_path, capsys):
    root = tmp_path / "screen"
    command = ["screen", "run", "--root", str(root), "--models", "td3_zoo", "--seeds", "1", "--tasks", "Pendulum-v1",
               "--stop-after", "100", "--workers", "1", "--checkpoint-freq", "0", "--no-progress"]  # fmt: skip
    assert main(command) == 2  # stopped (resumably) after 100 steps
    assert "1 interrupted" in capsys.readouterr().out
    status = json.loads((root / "Pendulum-v1" / "td3_zoo" / "seed_0" / STATUS_FILE).read_text())
    assert status["status"] == "interrupted" and status["step"] == 100
    assert list(json.loads((root / screen.RANDOM_SCORES_FILE).read_text())) == ["Pendulum-v1"]  # computed by the run
    grid = json.loads((root / "Pendulum-v1" / "grid.json").read_text())
    assert [run["model"] for run in grid["runs"]] == ["td3_zoo"] and "benchmark" in grid["suites"]

    assert main(["screen", "report", str(root), "--partial", "--to", str(tmp_path / "report"), "--tasks", "Pendulum-v1",
                 "--reps", str(REPS), "--improvement-over", "td3_zoo"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "- `td3_zoo` on Pendulum-v1: seed 0: interrupted at step 100/20000" in printed
    assert not (tmp_path / "report" / screen.RANDOM_SCORES_FILE).exists()  # read from the root's cache
    assert json.loads((tmp_path / "report" / screen.DATA_FILE).read_text())["improvement_over"] == ["td3_zoo"]
    assert main(["screen", "tasks"]) == 0 and "| Hopper-v4 | 50000 | 10000 |" in capsys.readouterr().out


def test_candidates_run_as_named_soup_models_the_same_runs_as_name_and_hyperparams(tmp_path):
    """`screen run --candidates FILE` runs each candidate as `--name NAME --hyperparams SETTINGS` would, in order."""
    candidates = tmp_path / "candidates.yml"
    candidates.write_text(
        "crit_redq: {train_heads: all_critics, target_q: redq, policy_delay: 2}\n"
        'layer_norm: {policy_kwargs: "dict(layer_norm=True)"}\n'
    )
    root = str(tmp_path / "screen")
    common = ["--root", root, "--seeds", "2", "--tasks", "Pendulum-v1,Hopper-v4"]
    specs = screen_specs(make_parser().parse_args(["screen", "run", "--candidates", str(candidates), *common]))
    assert [spec.model for spec in specs] == ["crit_redq"] * 4 + ["layer_norm"] * 4  # one candidate after the other
    by_hand = make_parser().parse_args(
        ["screen", "run", "--name", "crit_redq", "--hyperparams", "train_heads=all_critics", "target_q=redq",
         "policy_delay=2", *common]
    )  # fmt: skip
    assert [spec.config() for spec in specs[:4]] == [spec.config() for spec in screen_specs(by_hand)]
    assert specs[4].hyperparams["policy_kwargs"] == "dict(layer_norm=True)"
    assert specs[4].hyperparams["train_heads"] == soup_defaults()["train_heads"]  # the defaults, but for its settings
    # --only chooses, --hyperparams applies to every candidate
    only = make_parser().parse_args(
        ["screen", "run", "--candidates", str(candidates), "--only", "layer_norm", "--hyperparams", "batch_size=128", *common]
    )
    assert {(spec.model, spec.hyperparams["batch_size"]) for spec in screen_specs(only)} == {("layer_norm", 128)}


@pytest.mark.parametrize(
    "text, message",
    [
        ("- a\n- b\n", "must map each candidate's name to a mapping of its settings"),
        ("td3_zoo: {n_heads: 3}\n", "candidate names are folder names"),
        ("'a/b': {n_heads: 3}\n", "candidate names are folder names"),
    ],
)
def test_a_bad_candidates_file_is_refused(tmp_path, text, message):
    path = tmp_path / "candidates.yml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        grid.read_candidates(path)
    path.write_text("k3: {n_heads: 3}\n")
    with pytest.raises(ValueError, match=r"has no candidates \['k5'\]; it has \['k3'\]"):
        grid.read_candidates(path, ["k5"])
    for flags in (["--models", "td3_zoo"], ["--name", "x"]):
        args = make_parser().parse_args(["screen", "run", "--root", str(tmp_path), "--candidates", str(path), *flags])
        with pytest.raises(ValueError, match="drop --models and --name"):
            screen_specs(args)
    with pytest.raises(ValueError, match="--only chooses among --candidates"):
        screen_specs(make_parser().parse_args(["screen", "run", "--root", str(tmp_path), "--only", "k3"]))


def test_the_committed_candidates_are_all_valid_soup_settings():
    from sb3_soup import SOUP
    from sb3_soup.experiments.runner import resolve_policy_kwargs

    path = Path(__file__).resolve().parents[1] / "docs" / "results" / "screen" / "candidates.yml"
    candidates = grid.read_candidates(path)
    assert len(candidates) >= 10
    for settings in candidates.values():
        kwargs = dict(settings, policy_kwargs=resolve_policy_kwargs(settings.get("policy_kwargs")))
        SOUP("MlpPolicy", "Pendulum-v1", **kwargs)  # built as the runner builds it: no error
