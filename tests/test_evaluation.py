"""Deterministic evaluations: the runner's evaluations.csv, and the report's rliable statistics (IQM, P(improvement))."""

import json

import numpy as np
import pytest

from sb3_soup.experiments import evaluation, logs
from sb3_soup.experiments.__main__ import main
from sb3_soup.experiments.grid import build_grid
from sb3_soup.experiments.report import make_report
from sb3_soup.experiments.runner import DONE_FILE, STATUS_FILE, evaluation_seed

REPS = 200  # bootstrap resamples: enough for the checks, fast


def test_iqm_is_the_mean_of_the_middle_half_with_a_bootstrap_interval():
    estimate = evaluation.iqm(np.arange(1.0, 9.0), reps=REPS)  # middle half: 3, 4, 5, 6
    assert estimate.value == pytest.approx(4.5)
    assert estimate.low <= 4.5 <= estimate.high and estimate.low < estimate.high
    assert evaluation.iqm(np.array([1.0, 2.0, 3.0, 1000.0]), reps=REPS).value == pytest.approx(2.5)  # robust to an outlier


def test_probability_of_improvement():
    assert evaluation.probability_of_improvement(np.array([10.0, 11, 12]), np.array([1.0, 2, 3]), reps=REPS).value == 1.0
    assert evaluation.probability_of_improvement(np.array([1.0, 2, 3]), np.array([10.0, 11, 12]), reps=REPS).value == 0.0
    assert evaluation.probability_of_improvement(np.array([5.0, 5]), np.array([5.0, 5]), reps=REPS).value == 0.5  # ties: half
    mixed = evaluation.probability_of_improvement(np.array([1.0, 4.0]), np.array([2.0, 3.0]), reps=REPS)
    assert mixed.value == pytest.approx(0.5) and 0.0 <= mixed.low <= mixed.high <= 1.0


def test_evaluations_file_roundtrip_and_truncation(tmp_path):
    logs.append_evaluation(tmp_path, 100, [1.0, 3.0], [10, 12])
    logs.append_evaluation(tmp_path, 200, [5.0, 7.0], [10, 10])
    steps, means = evaluation.read_run(str(tmp_path))
    assert steps.tolist() == [100, 200] and means.tolist() == [2.0, 6.0]
    logs.truncate_evaluations(tmp_path, 150)  # a resume from step 150 drops what came after
    assert evaluation.read_run(str(tmp_path))[0].tolist() == [100]


def test_evaluation_seeds_depend_on_the_run_seed_and_the_step_only():
    assert evaluation_seed(0, 10_000) == evaluation_seed(0, 10_000)
    assert len({evaluation_seed(seed, step) for seed in (0, 1) for step in (10_000, 20_000)}) == 4


def _evaluated_run(spec, means: dict[int, float]) -> None:
    """A finished run folder whose evaluation at each step has two episodes averaging ``means[step]``."""
    run_dir = spec.run_dir
    from pathlib import Path

    path = Path(run_dir)
    path.mkdir(parents=True)
    (path / "spec.json").write_text(spec.to_json())
    (path / STATUS_FILE).write_text(json.dumps({"status": "finished", "step": spec.timesteps, "total": spec.timesteps}))
    (path / DONE_FILE).write_text(json.dumps({"timesteps": spec.timesteps}))
    (path / logs.MONITOR_FILE).write_text('#{"t_start": 0}\nr,l,t\n1.0,10,0.0\n')
    for step, mean in means.items():
        logs.append_evaluation(path, step, [mean - 1.0, mean + 1.0], [1000, 1000])


def test_report_writes_the_evaluation_statistics(tmp_path):
    out = tmp_path / "runs"
    specs = build_grid("Hopper-v4", out, suite="benchmark", models=["ddpg_zoo", "td3_zoo"], seeds=[0, 1, 2], timesteps=20)
    for spec in specs:
        good = spec.model == "td3_zoo"
        _evaluated_run(spec, {10: 100.0 * spec.seed, 20: (1000.0 if good else 10.0) + spec.seed})
    data = make_report(out, suite="benchmark", bootstrap_reps=REPS)
    table = (out / "report-benchmark" / "evaluation.md").read_text()
    assert "evaluation.png" in data["files"]
    hopper = data["evaluation"]["Hopper-v4"]
    assert hopper["step"] == 20 and hopper["baseline"] == "ddpg_zoo"
    td3 = hopper["models"]["td3_zoo"]
    assert td3["scores"] == [1000.0, 1001.0, 1002.0] and td3["iqm"]["value"] == pytest.approx(1001.0)
    assert td3["probability_of_improvement"]["value"] == 1.0
    assert hopper["models"]["ddpg_zoo"]["probability_of_improvement"] is None
    assert "| Hopper-v4 | DDPG (RL Zoo) | 20 | 3 | 11 [10, 12] | 11 ± 1 | (baseline) |" in table

    # an earlier step, and runs from another folder (e.g. baselines trained for longer)
    at_10 = make_report(out, suite="benchmark", eval_step=10, bootstrap_reps=REPS)["evaluation"]["Hopper-v4"]
    assert at_10["models"]["td3_zoo"]["scores"] == [0.0, 100.0, 200.0]
    other = tmp_path / "more"
    (spec,) = build_grid("Hopper-v4", other, models=["soup"], seeds=[0], timesteps=10, name="soup-short")
    _evaluated_run(spec, {10: 500.0})
    joined = make_report(out, suite=None, baseline="ddpg_zoo", eval_step=10, extra=[other], bootstrap_reps=REPS)["evaluation"][
        "Hopper-v4"
    ]
    assert joined["models"]["soup-short"]["scores"] == [500.0]
    with pytest.raises(ValueError, match="both hold the runs"):
        make_report(out, extra=[out])


def test_an_unfinished_run_joins_the_evaluation_at_the_steps_it_reached(tmp_path):
    """With ``partial``, a run still training counts at the steps it has evaluated; its model is not dropped."""
    out = tmp_path / "runs"
    specs = build_grid("Hopper-v4", out, suite="benchmark", models=["ddpg_zoo"], seeds=[0, 1], timesteps=20)
    _evaluated_run(specs[0], {10: 100.0, 20: 200.0})
    _evaluated_run(specs[1], {10: 300.0})  # stopped after its first evaluation
    status = {"status": "interrupted", "step": 15, "total": 20}
    (out / "ddpg_zoo" / "seed_1" / STATUS_FILE).write_text(json.dumps(status))
    (out / "ddpg_zoo" / "seed_1" / DONE_FILE).unlink()
    at = {step: make_report(out, partial=True, eval_step=step, bootstrap_reps=REPS)["evaluation"] for step in (10, 20)}
    at = {step: data["Hopper-v4"] for step, data in at.items()}
    assert at[10]["models"]["ddpg_zoo"]["scores"] == [100.0, 300.0]
    assert at[20]["models"]["ddpg_zoo"]["scores"] == [200.0] and at[20]["models"]["ddpg_zoo"]["seeds"] == [0]


def test_a_score_can_average_the_last_evaluations_up_to_the_step(tmp_path, capsys):
    """``--eval-last N``: a run's score is the mean of its last N evaluations up to the step, not the step's alone."""
    out = tmp_path / "runs"
    specs = build_grid("Hopper-v4", out, suite="benchmark", models=["ddpg_zoo", "td3_zoo"], seeds=[0, 1], timesteps=40)
    for spec in specs:
        base = 1000.0 if spec.model == "td3_zoo" else 0.0
        _evaluated_run(spec, {10: base + 10.0, 20: base + 20.0 + spec.seed, 30: base + 60.0, 40: base + 100.0})
    hopper = make_report(out, suite="benchmark", eval_last=3, bootstrap_reps=REPS)["evaluation"]["Hopper-v4"]
    assert hopper["step"] == 40 and hopper["steps_averaged"] == [20, 30, 40]
    assert hopper["models"]["td3_zoo"]["scores"] == [1060.0, pytest.approx(1060.0 + 1 / 3)]  # (20 + s + 60 + 100) / 3
    assert hopper["models"]["ddpg_zoo"]["scores"] == [60.0, pytest.approx(60.0 + 1 / 3)]
    table = (out / "report-benchmark" / "evaluation.md").read_text()
    assert "| Hopper-v4 | DDPG (RL Zoo) | 20-40 | 2 |" in table
    assert "A run's score: the mean of its last 3 evaluations up to the step" in table
    # up to an earlier step; the default (1) is the step's evaluation alone
    at_30 = make_report(out, suite="benchmark", eval_step=30, eval_last=2, bootstrap_reps=REPS)["evaluation"]["Hopper-v4"]
    assert at_30["steps_averaged"] == [20, 30] and at_30["models"]["ddpg_zoo"]["scores"] == [40.0, 40.5]
    assert make_report(out, suite="benchmark", bootstrap_reps=REPS)["evaluation"]["Hopper-v4"]["steps_averaged"] == [40]

    with pytest.raises(ValueError, match="fewer than the 5"):
        make_report(out, suite="benchmark", eval_last=5, bootstrap_reps=REPS)
    with pytest.raises(ValueError, match="whole number >= 1, got 0"):
        make_report(out, suite="benchmark", eval_last=0, bootstrap_reps=REPS)
    for bad in ("0", "-2", "two"):
        with pytest.raises(SystemExit):
            main(["report", str(out), "--eval-last", bad])
        assert "--eval-last: expected a whole number >= 1" in capsys.readouterr().err
    assert main(["report", str(out), "--suite", "benchmark", "--eval-last", "4", "--reps", str(REPS)]) == 0
    assert "| TD3 (RL Zoo) | 10-40 | 2 | 1048 " in capsys.readouterr().out  # (10 + 20.5 + 60 + 100) / 4 + 1000, IQM
