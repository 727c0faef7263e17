"""
Tests of the experiment runner (sb3_soup.experiments): grid, metrics, checkpoints, logs, run/resume, shared runs
between suites, progress display, report, Ray backend.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from sb3_soup import SOUP, DecayingNormalActionNoise
from sb3_soup.checkpoint import latest_checkpoint
from sb3_soup.experiments import logs
from sb3_soup.experiments.__main__ import main
from sb3_soup.experiments.grid import (
    SUITES,
    VARIANTS,
    RunSpec,
    build_grid,
    load_hyperparams,
    parse_overrides,
    parse_seeds,
    suite_columns,
)
from sb3_soup.experiments.metrics import add_speed_ups, first_crossing, model_metrics, running_average, speed_up
from sb3_soup.experiments.parallel import available_cores, run_grid
from sb3_soup.experiments.progress import ProgressBoard, progress_mode
from sb3_soup.experiments.report import collect_runs, make_report, write_grid
from sb3_soup.experiments.runner import (
    CHECKPOINT_DIR,
    DONE_FILE,
    ERROR_FILE,
    STATUS_FILE,
    build_model,
    busy_reason,
    is_finished,
    run_lock,
    run_one,
)
from sb3_soup.presets import resolve_model

# Two cheap models: SOUP's DDPG preset and SOUP (adaptive confidence), with small networks.
MODELS = "ddpg,soup"
FAST = [
    "learning_starts=50",
    "batch_size=32",
    "buffer_size=5000",
    "policy_kwargs=dict(net_arch=dict(pi_body=[32], pi_head=[16], qf_body=[32, 32], qf_head=[16]))",
]


# ---------------------------------------------------------------- metrics on hand-made curves


def test_running_average():
    returns = [1.0, 3.0, 5.0, 7.0]
    np.testing.assert_allclose(running_average(returns, window=2), [1.0, 2.0, 4.0, 6.0])
    np.testing.assert_allclose(running_average(returns, window=None), [1.0, 2.0, 3.0, 4.0])
    np.testing.assert_allclose(running_average(returns, window=10), [1.0, 2.0, 3.0, 4.0])


def test_first_crossing_and_speed_up():
    assert first_crossing([0, 1999, 2000, 3000], 2000) == 3  # 1-based, >= threshold
    assert first_crossing([0, 1], 2000) is None
    assert first_crossing([0, 1], None) is None
    assert speed_up(50, 100) == pytest.approx(0.5)
    assert speed_up(None, 100) is None and speed_up(50, None) is None


def test_model_metrics_hand_made():
    # Hopper thresholds: Episode 2000, Speed Up 1000; running-average window 2.
    seed_0 = [0.0, 1000.0, 2500.0, 500.0]  # mean 1000; first >= 2000 at episode 3; running avg 0,500,1750,1500 -> E 3
    seed_1 = [100.0, 2100.0, 3000.0, 3000.0]  # mean 2050; episode 2; running avg 100,1100,... -> E 2
    metrics = model_metrics([seed_0, seed_1], 2000, 1000, window=2, seeds=[0, 1])
    assert metrics.n_seeds == 2
    assert metrics.avg_return == pytest.approx((1000 + 2050) / 2)
    assert metrics.avg_return_std == pytest.approx(np.std([1000, 2050]))  # ddof=0: 525
    assert metrics.avg_return_std == pytest.approx(525.0)
    assert metrics.max_return == 3000.0
    assert metrics.episode == pytest.approx(2.5) and metrics.episode_crossed == 2
    assert metrics.speedup_episode == pytest.approx(2.5) and metrics.speedup_crossed == 2
    assert [entry["episode"] for entry in metrics.per_seed] == [3, 2]

    # A seed that never crosses is left out of the mean and counted.
    slow = model_metrics([[0.0] * 5, [0.0, 0.0, 0.0, 1500.0, 1500.0]], 2000, 1000, window=2)
    assert slow.episode is None and slow.episode_crossed == 0
    assert slow.speedup_episode == 5 and slow.speedup_crossed == 1

    table = {"ddpg": slow, "soup": metrics}
    add_speed_ups(table, "ddpg")
    assert table["soup"].speed_up == pytest.approx(1 - 2.5 / 5)
    assert table["ddpg"].speed_up is None


def test_running_average_window_changes_the_crossing():
    # Window 3 by hand: (10)/1, (10+0)/2, (10+0+50)/3, (0+50+40)/3, (50+40+0)/3 = 10, 5, 20, 30, 30.
    returns = [10.0, 0.0, 50.0, 40.0, 0.0]
    np.testing.assert_allclose(running_average(returns, window=3), [10.0, 5.0, 20.0, 30.0, 30.0])
    # Cumulative: 10, 5, 20, 25, 20.
    np.testing.assert_allclose(running_average(returns, window=None), [10.0, 5.0, 20.0, 25.0, 20.0])
    assert first_crossing(running_average(returns, window=3), 30) == 4
    assert first_crossing(running_average(returns, window=None), 30) is None


# ---------------------------------------------------------------- report on hand-made runs (no training)


def _fake_run(spec: RunSpec, returns, state: str = "finished", confidence=None, step: int | None = None) -> None:
    """A run folder as the runner leaves it, with the given training-episode returns (episodes of 10 steps)."""
    run_dir = Path(spec.run_dir)
    run_dir.mkdir(parents=True)
    (run_dir / "spec.json").write_text(spec.to_json())
    rows = "".join(f"{value},10,{index}.0\n" for index, value in enumerate(returns))
    (run_dir / logs.MONITOR_FILE).write_text('#{"t_start": 0, "env_id": "Hopper-v4"}\nr,l,t\n' + rows)
    step = 10 * len(returns) if step is None else step
    status = {"finished": "finished", "failed": "failed", "interrupted": "interrupted", "running": "running"}[state]
    (run_dir / STATUS_FILE).write_text(
        json.dumps({"status": status, "step": step, "total": spec.timesteps, "time": time.time()})
    )
    if state == "finished":
        (run_dir / DONE_FILE).write_text(json.dumps({"timesteps": spec.timesteps, "episodes": len(returns)}))
    if state == "failed":
        (run_dir / ERROR_FILE).write_text(json.dumps({"error": "RuntimeError: boom"}))
    if confidence is not None:  # progress.csv with the per-head confidence of an adaptive run
        lines = ["time/total_timesteps,confidence/head_0,confidence/head_1"]
        lines += [f"{10 * (i + 1)},{c0},{c1}" for i, (c0, c1) in enumerate(confidence)]
        (run_dir / logs.PROGRESS_FILE).write_text("\n".join(lines) + "\n")


def _row(table: str, metric: str) -> list[str]:
    line = next(line for line in table.splitlines() if f"| {metric} |" in line)
    return [cell.strip() for cell in line.strip("|").split("|")][2:]


@pytest.fixture
def hand_made(tmp_path):
    """
    A Hopper-v4 folder (thresholds 2000 / 1000) of hand-made runs. With a running-average window of 2:

    - ddpg seed 0: 0, 1000, 2500, 500 -> mean 1000; first >= 2000: episode 3; running avg 0, 500, 1750 -> E 3
    - ddpg seed 1: 300, 900, 2100, 1500 -> mean 1200; episode 3; running avg 300, 600, 1500 -> E 3
    - soup seed 0: 1200, 2400, 3000 -> mean 2200; episode 2; running avg 1200 -> E 1
    - soup seed 1: 0, 1200, 600 -> mean 600; never >= 2000; running avg 0, 600, 900 -> never
    - soup seed 2: interrupted after 1500, 5000 -> mean 3250; episode 2; running avg 1500 -> E 1
    - td3 seed 0 failed, td3 seed 1 never started.
    """
    out = tmp_path / "hopper"
    specs = build_grid("Hopper-v4", out, models=["ddpg", "soup", "td3"], heads=[2], seeds=[0, 1, 2], timesteps=1000)
    write_grid(out, [spec for spec in specs if spec.model == "soup-k2" or spec.seed < 2], "models", [2])
    runs = {spec.key: spec for spec in specs}
    _fake_run(runs["ddpg/seed_0"], [0, 1000, 2500, 500])
    _fake_run(runs["ddpg/seed_1"], [300, 900, 2100, 1500])
    confidence = [(0.2, 0.8), (0.3, 0.7), (0.4, 0.6)]
    _fake_run(runs["soup-k2/seed_0"], [1200, 2400, 3000], confidence=confidence)
    _fake_run(runs["soup-k2/seed_1"], [0, 1200, 600], confidence=confidence)
    _fake_run(runs["soup-k2/seed_2"], [1500, 5000], state="interrupted", step=400)
    _fake_run(runs["td3/seed_0"], [], state="failed", step=0)
    return out


def test_report_metrics_on_hand_made_runs(hand_made):
    data = make_report(hand_made, window=2)
    table = (hand_made / "table.md").read_text()
    assert table.splitlines()[0] == "| Env. | Metric | DDPG | SOUP (K=2) | TD3 |"
    # Finished runs only: soup's interrupted seed 2 is listed, not used.
    assert _row(table, "Avg Return") == ["1100 ± 100", "1400 ± 800", "n/a"]
    assert _row(table, "Max Return") == ["2500", "3000", "n/a"]
    assert _row(table, "Episode") == ["3", "2 (1/2)", "n/a"]
    assert _row(table, "E") == ["3", "1 (1/2)", "n/a"]
    assert _row(table, "Speed Up") == ["(baseline)", "0.67", "n/a"]  # 1 - 1/3
    assert _row(table, "Seeds") == ["2/2", "2/3", "0/2"]
    assert "**Not included (3 runs):**" in table
    assert "`soup-k2/seed_2`: interrupted (400/1000 steps)" in table
    assert "`td3/seed_0`: failed (0/1000 steps: RuntimeError: boom)" in table
    assert "`td3/seed_1`: not started" in table
    assert "report --partial" in table

    soup = data["metrics"]["Hopper-v4"]["soup-k2"]
    assert soup["avg_return"] == 1400 and soup["avg_return_std"] == 800 and soup["speed_up"] == pytest.approx(2 / 3)
    assert [entry["episode"] for entry in soup["per_seed"]] == [2, None]
    assert data["thresholds"]["Hopper-v4"] == {"episode": 2000.0, "speed_up": 1000.0} and data["baseline"] == "ddpg"
    assert sorted(data["not_included"]) == ["Hopper-v4:soup-k2/seed_2", "Hopper-v4:td3/seed_0", "Hopper-v4:td3/seed_1"]
    assert data["partial"] == [] and set(data["files"]) == {"table.md", "metrics.json", "curves.png", "confidence.png"}
    for name in data["files"]:
        assert (hand_made / name).stat().st_size > 0


def test_report_partial_marks_unfinished_runs(hand_made, tmp_path):
    data = make_report(hand_made, window=2, partial=True, report_dir=tmp_path / "partial")
    table = (tmp_path / "partial" / "table.md").read_text()
    assert table.splitlines()[0] == "| Env. | Metric | DDPG | SOUP (K=2) † | TD3 |"
    # Seed 2 (1500, 5000) joins: means 2200, 600, 3250 -> 2016.7 ± 1089.6 (ddof=0); episodes 2, never, 2.
    assert _row(table, "Avg Return") == ["1100 ± 100", "2017 ± 1090", "n/a"]
    assert _row(table, "Max Return") == ["2500", "5000", "n/a"]
    assert _row(table, "Episode") == ["3", "2 (2/3)", "n/a"]
    assert _row(table, "Seeds") == ["2/2", "3/3", "0/2"]
    assert "† Partial: 1 unfinished runs are included" in table and "`soup-k2/seed_2`: interrupted" in table
    assert data["partial"] == ["soup-k2"]
    assert sorted(data["not_included"]) == ["Hopper-v4:td3/seed_0", "Hopper-v4:td3/seed_1"]
    assert [entry["status"] for entry in data["metrics"]["Hopper-v4"]["soup-k2"]["per_seed"]] == [
        "finished",
        "finished",
        "interrupted",
    ]


def test_report_thresholds_and_baseline_options(hand_made, tmp_path):
    # Thresholds 2400 / 700 and the cumulative mean as running average:
    # Episode: ddpg seed 0 (0, 1000, 2500) -> 3, seed 1 never; soup seed 0 (1200, 2400) -> 2, seed 1 never.
    # E: ddpg seed 0 (0, 500, 1167) -> 3, seed 1 (300, 600, 1100) -> 3; soup seed 0 (1200) -> 1, seed 1 (0, 600, 600)
    # never. Speed Up = 1 - 1/3.
    assert main(["report", str(hand_made), "--threshold", "2400", "--speedup-threshold", "700", "--window", "0"]) == 0
    table = (hand_made / "table.md").read_text()
    assert _row(table, "Episode") == ["3 (1/2)", "2 (1/2)", "n/a"]
    assert _row(table, "E") == ["3", "1 (1/2)", "n/a"]
    assert _row(table, "Speed Up") == ["(baseline)", "0.67", "n/a"]
    # Window 2 instead: soup seed 1's running average is 0, 600, 900 -> E 3, so soup's E is (1 + 3) / 2 = 2; with soup
    # as the baseline, DDPG's Speed Up is 1 - 3/2.
    assert main(["report", str(hand_made), "--speedup-threshold", "700", "--window", "2", "--baseline", "soup-k2",
                 "--to", str(tmp_path / "vs-soup")]) == 0  # fmt: skip
    table = (tmp_path / "vs-soup" / "table.md").read_text()
    assert _row(table, "E") == ["3", "2", "n/a"]
    assert _row(table, "Speed Up") == ["-0.50", "(baseline)", "n/a"]
    data = json.loads((tmp_path / "vs-soup" / "metrics.json").read_text())
    assert data["thresholds"]["Hopper-v4"] == {"episode": 2000.0, "speed_up": 700.0}  # the Episode one stays the paper's
    assert data["baseline"] == "soup-k2" and data["window"] == 2


# ---------------------------------------------------------------- grid and hyper-parameters


def test_grid_suites_and_overrides(tmp_path):
    specs = build_grid("Pendulum-v1", tmp_path, suite="models", seeds=[0, 1], timesteps=100)
    assert [spec.model for spec in specs[::2]] == ["ddpg", "ma_bddpg-k5", "multi_ddpg-k5", "dbddpg-k5", "soup-k5", "td3"]
    assert specs[2].hyperparams["preset"] == "ma_bddpg" and specs[2].hyperparams["n_heads"] == 5
    # DDPG is the one-head preset, whatever K the env's soup.yml entry gives (Pendulum-v1's says 5)
    ddpg = specs[0].hyperparams
    assert ddpg["preset"] == "ddpg"
    settings = resolve_model(ddpg.get("n_heads", 1), None, None, ddpg["preset"], None, None)
    assert (settings["n_actor_heads"], settings["n_critic_heads"], settings["mask_prob"]) == (1, 1, 1.0)
    td3 = specs[-1].hyperparams
    assert td3["policy_kwargs"] == {"net_arch": [256, 256]} and "preset" not in td3 and "critic_learning_rate" not in td3
    assert td3["gamma"] == specs[0].hyperparams["gamma"] and td3["batch_size"] == specs[0].hyperparams["batch_size"]

    heads = build_grid("Pendulum-v1", tmp_path, suite="heads", seeds=[0], timesteps=100)
    assert [spec.model for spec in heads] == ["soup-k3", "soup-k5", "soup-k10"]
    confidence = build_grid("Pendulum-v1", tmp_path, suite="confidence", models=["fixed"], heads=[3], seeds=[0], timesteps=100)
    assert confidence[0].model == "fixed-k3" and confidence[0].hyperparams["confidence"] == "fixed"
    assert confidence[0].label == "Fixed confidence (K=3)"

    overrides = parse_overrides(["batch_size=64", "soup:tau=0.01", "td3:learning_rate=1e-3", "policy_kwargs=dict(a=1)"])
    assert overrides == {
        "*": {"batch_size": 64, "policy_kwargs": "dict(a=1)"},
        "soup": {"tau": 0.01},
        "td3": {"learning_rate": 1e-3},
    }
    specs = build_grid("Pendulum-v1", tmp_path, models=["soup", "td3"], seeds=[0], timesteps=100, overrides=overrides)
    assert specs[0].hyperparams["batch_size"] == 64 and specs[0].hyperparams["tau"] == 0.01
    assert specs[1].hyperparams["batch_size"] == 64 and specs[1].hyperparams["learning_rate"] == 1e-3
    assert parse_seeds("3") == [0, 1, 2] and parse_seeds("4,7") == [4, 7] and parse_seeds("0,") == [0]
    with pytest.raises(ValueError, match="Unknown model"):
        build_grid("Pendulum-v1", tmp_path, models=["nope"])
    assert set(VARIANTS) >= {"ddpg", "ma_bddpg", "multi_ddpg", "dbddpg", "soup", "td3", "none", "fixed", "decayed", "adaptive"}


@pytest.mark.parametrize("text", ["0", "-2", ",", "1,-1", "2,2", "x"])
def test_seeds_that_select_no_run_or_collide_are_refused_with_the_accepted_forms(text):
    # "--seeds 0" is a count of none (seed 0 alone is "0,"): it used to select no run and crash the report
    with pytest.raises(ValueError, match=r"seeds=.*a count of at least 1 .* or a comma-separated list"):
        parse_seeds(text)


def test_seeds_errors_reach_the_command_line(capsys):
    with pytest.raises(SystemExit):
        main(["screen", "report", "runs/screen", "--seeds", "0"])
    assert "for seed 0 alone write 0," in capsys.readouterr().err


def test_benchmark_suite_runs_what_peers_publish(tmp_path):
    """One command per env: SOUP's defaults and TD3 with 5 seeds, the paper's SOUP, DDPG and SAC with 3 (issue 19)."""
    specs = build_grid("Hopper-v4", tmp_path, suite="benchmark", timesteps=200_000)
    seeds: dict[str, list[int]] = {}
    for spec in specs:
        seeds.setdefault(spec.variant, []).append(spec.seed)
    assert seeds == {
        "soup_defaults": [0, 1, 2, 3, 4],
        "soup": [0, 1, 2],  # the paper's SOUP, stored as the models suite's soup
        "ddpg_zoo": [0, 1, 2],
        "td3_zoo": [0, 1, 2, 3, 4],
        "sac_zoo": [0, 1, 2],
    }
    assert {spec.timesteps for spec in specs} == {200_000} and {spec.eval_freq for spec in specs} == {10_000}
    # given seeds are every model's
    given = build_grid("Hopper-v4", tmp_path, suite="benchmark", models=["td3_zoo", "sac_zoo"], seeds=[7], timesteps=100)
    assert [(spec.model, spec.seed) for spec in given] == [("td3_zoo", 7), ("sac_zoo", 7)]


def test_a_soup_spec_records_its_networks_so_a_default_change_does_not_reuse_old_runs(tmp_path, monkeypatch):
    import sb3_soup.policies

    defaults, td3 = build_grid("Pendulum-v1", tmp_path, suite="benchmark", models=["soup_defaults", "td3_zoo"], seeds=[0])
    assert "policy_kwargs" not in defaults.hyperparams  # SOUP's defaults: the networks are the default ones...
    assert defaults.net_arch == dict(pi_body=[256], pi_head=[128], qf_body=[256, 256], qf_head=[128], qf_action_layer=1)
    assert td3.net_arch is None  # ...and the spec says which (SB3's algorithms: their hyperparams say it)
    candidate = build_grid(
        "Pendulum-v1", tmp_path, suite="benchmark", models=["soup_defaults"], seeds=[0], name="sb3_critic",
        overrides=parse_overrides(["policy_kwargs=dict(net_arch=dict(qf_action_layer=0, qf_body=[64]))"]),
    )[0]  # fmt: skip
    assert candidate.net_arch == dict(pi_body=[256], pi_head=[128], qf_body=[64], qf_head=[128], qf_action_layer=0)

    # A spec.json written before specs recorded the networks (no net_arch) trained the critic of then, where the action
    # joined at the second layer unless its net_arch said otherwise
    def finished_before(spec: RunSpec) -> None:
        Path(spec.run_dir).mkdir(parents=True)
        data = dataclasses.asdict(spec)
        del data["net_arch"]
        (Path(spec.run_dir) / "spec.json").write_text(json.dumps(data))
        (Path(spec.run_dir) / DONE_FILE).write_text("{}")

    finished_before(defaults)
    finished_before(candidate)
    assert is_finished(defaults) and is_finished(candidate)
    monkeypatch.setattr(sb3_soup.policies, "DEFAULT_ACTION_LAYER", 0)  # were the default critic SB3's...
    defaults_now = build_grid("Pendulum-v1", tmp_path, suite="benchmark", models=["soup_defaults"], seeds=[0])[0]
    assert defaults_now.net_arch["qf_action_layer"] == 0
    assert not is_finished(defaults_now)  # ...the old defaults' run would not count as the new defaults'
    assert "differs in: net_arch" in run_one(dataclasses.asdict(defaults_now))["error"]
    assert is_finished(candidate)  # a run whose net_arch said where the action joins keeps its meaning


def test_confidence_suite_shares_the_models_suites_runs(tmp_path):
    models = {spec.key: spec for spec in build_grid("Hopper-v4", tmp_path, suite="models", seeds=[0])}
    confidence = build_grid("Hopper-v4", tmp_path, suite="confidence", seeds=[0])
    # "none" and "adaptive" are stored as the models suite's dbddpg and soup: same folder, same spec, same identity.
    assert [spec.model for spec in confidence] == ["dbddpg-k5", "fixed-k5", "decayed-k5", "soup-k5"]
    assert confidence[0] == models["dbddpg-k5/seed_0"] and confidence[3] == models["soup-k5/seed_0"]
    assert confidence[1].hyperparams["confidence"] == "fixed" and "preset" not in confidence[1].hyperparams
    # An override aimed at the variant by name makes it a run of its own; one for every model keeps them shared.
    apart = build_grid("Hopper-v4", tmp_path, suite="confidence", seeds=[0], overrides=parse_overrides(["none:tau=0.01"]))
    assert apart[0].model == "none-k5" and apart[0].label == "No confidence (K=5)" and apart[3].model == "soup-k5"
    shared = build_grid("Hopper-v4", tmp_path, suite="confidence", seeds=[0], overrides=parse_overrides(["tau=0.01"]))
    assert shared[0].model == "dbddpg-k5"
    # A run's identity is its settings, not its names: a spec.json written with other names still matches.
    renamed = dataclasses.replace(confidence[0], label="DBDDPG, renamed", variant="old-name", run_dir="elsewhere")
    assert renamed.config() == confidence[0].config()
    assert dataclasses.replace(confidence[0], seed=1).config() != confidence[0].config()


def test_every_suite_variant_builds_the_model_it_names():
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    expected = {  # (actor heads, critic heads, confidence, bootstrap masks on) at K=3, soup-spec.md's model table
        "ddpg": (1, 1, "none", False),
        "ma_bddpg": (1, 3, "none", True),
        "multi_ddpg": (3, 1, "none", True),
        "dbddpg": (3, 3, "none", True),
        "soup": (3, 3, "adaptive", True),
        "none": (3, 3, "none", True),
        "fixed": (3, 3, "fixed", True),
        "decayed": (3, 3, "decayed", True),
        "adaptive": (3, 3, "adaptive", True),
        "soup_paper": (3, 3, "adaptive", True),
    }
    env = DummyVecEnv([lambda: gym.make("Pendulum-v1")])
    small = parse_overrides(
        ["buffer_size=100", "policy_kwargs=dict(net_arch=dict(pi_body=[8], pi_head=[8], qf_body=[8, 8], qf_head=[8]))"]
    )
    for suite in SUITES:
        for spec in build_grid("Pendulum-v1", "unused", suite=suite, heads=[3], seeds=[0], overrides=small):
            if spec.algo != "soup":
                continue
            name = next(variant for variant in SUITES[suite].variants if spec.variant in (variant, VARIANTS[variant].same_as))
            model = build_model(spec, env)
            settings = (model.n_actor_heads, model.n_critic_heads, model.confidence, model.mask_prob < 1)
            if name == "soup_defaults":  # what SOUP("MlpPolicy", env) builds, whatever K the suite has
                default = SOUP("MlpPolicy", env, _init_setup_model=False)
                expected[name] = (default.n_actor_heads, default.n_critic_heads, default.confidence, default.mask_prob < 1)
            assert settings == expected[name], (suite, name)
            # the paper's family trains with the paper's update; SOUP's defaults with theirs
            scheme = (model.train_heads, model.target_q, model.policy_delay, model.target_policy_noise)
            paper_scheme, default_scheme = ("active", "own", 1, 0.0), ("all", "min_pair", 2, 0.2)
            assert scheme == (paper_scheme if VARIANTS[spec.variant].source == "paper" else default_scheme), (suite, name)
            # the paper's decaying noise (soup_paper.yml's noise_type 'decaying_normal'), or SOUP's default N(0, 0.1)
            noise, paper = model.action_noise, VARIANTS[spec.variant].source == "paper"
            assert isinstance(noise, DecayingNormalActionNoise), (suite, name)
            assert (noise.sigma[0], noise.decay, noise.sigma_min) == ((0.2, 0.999995, 0.05) if paper else (0.1, 1.0, 0.0))
    env.close()


def test_hyperparams_file(tmp_path):
    file = tmp_path / "soup.yml"
    file.write_text(
        "Hopper-v4:\n  n_timesteps: !!float 1e6\n  policy: 'MlpPolicy'\n  normalize: true\n  n_envs: 1\n"
        '  batch_size: 1024\n  policy_kwargs: "dict(net_arch=dict(pi_body=[256]))"\n  n_heads: 7\n'
    )
    params = load_hyperparams("Hopper-v4", file)
    assert params == {"batch_size": 1024, "policy_kwargs": "dict(net_arch=dict(pi_body=[256]))", "n_heads": 7}
    assert load_hyperparams("Pendulum-v1", file)["batch_size"] == 256  # fallback for envs not in the file
    specs = build_grid("Hopper-v4", tmp_path, models=["soup"], heads=[3], seeds=[0], hyperparams_file=file)
    assert specs[0].timesteps == 1_000_000 and specs[0].hyperparams["n_heads"] == 3  # the suite's K wins


# ---------------------------------------------------------------- logs


def test_logs_continue_after_truncation(tmp_path):
    (tmp_path / logs.MONITOR_FILE).write_text('#{"t_start": 0}\nr,l,t\n1.0,10,0.1\n2.0,10,0.2\n3.0,10,0.3\n')
    logs.truncate_monitor(tmp_path, 25)  # the episodes that ended by step 25: at steps 10 and 20
    assert logs.count_episodes(tmp_path) == 2
    assert list(logs.read_monitor(tmp_path)["r"]) == [1.0, 2.0]

    logger = logs.make_logger(tmp_path)
    for step in (100, 200, 300):
        logger.record("time/total_timesteps", step)
        logger.record("rollout/ep_rew_mean", -step)
        logger.dump(step)
    logger.close()
    logs.truncate_progress(tmp_path, 200)
    logger = logs.make_logger(tmp_path)  # continues the file, and may add a column
    logger.record("time/total_timesteps", 250)
    logger.record("confidence/head_0", 0.5)
    logger.dump(250)
    logger.close()
    frame = logs.read_progress(tmp_path)
    assert list(frame["time/total_timesteps"]) == [100, 200, 250]
    assert frame["confidence/head_0"].isna().tolist() == [True, True, False]


# ---------------------------------------------------------------- runs: failure isolation, end to end, resume


def _run_in_thread(target, *args, **kwargs):
    """Start ``target`` in a thread; return the thread and a dict that gets its return value as ``"value"``."""
    box: dict = {}
    thread = threading.Thread(target=lambda: box.update(value=target(*args, **kwargs)), daemon=True)
    thread.start()
    return thread, box


def _wait_for(predicate, timeout: float = 300.0) -> None:
    deadline = time.time() + timeout
    while not predicate():
        assert time.time() < deadline, "timed out"
        time.sleep(0.1)


def test_failing_and_killed_runs_are_reported_and_others_finish(tmp_path):
    good, bad, victim = build_grid(
        "Pendulum-v1", tmp_path, models=["td3", "sb3_ddpg"], seeds=[0, 1], timesteps=120, overrides=parse_overrides(FAST[:3])
    )[:3]
    bad = dataclasses.replace(bad, hyperparams={**bad.hyperparams, "not_a_parameter": 1})
    victim = dataclasses.replace(victim, timesteps=1_000_000)  # killed long before its end
    status_file = Path(victim.run_dir) / STATUS_FILE
    thread, box = _run_in_thread(run_grid, [good, bad, victim], workers=3, progress=False)
    _wait_for(lambda: status_file.is_file() and json.loads(status_file.read_text()).get("status") == "running")
    os.kill(json.loads(status_file.read_text())["pid"], signal.SIGKILL)  # e.g. the out-of-memory killer
    thread.join(120)
    results = box["value"]
    assert [result["status"] for result in results] == ["finished", "failed", "failed"]
    assert "not_a_parameter" in results[1]["error"]
    assert "not_a_parameter" in json.loads((Path(bad.run_dir) / ERROR_FILE).read_text())["traceback"]
    assert "killed by SIGKILL" in results[2]["error"]
    assert "SIGKILL" in json.loads((Path(victim.run_dir) / ERROR_FILE).read_text())["error"]
    assert json.loads(status_file.read_text())["wall_time_s"] > 0  # the time it spent is kept with its failure
    assert (Path(good.run_dir) / DONE_FILE).is_file()
    # The same spec run again in-process fails the same way, and its folder keeps refusing other settings.
    assert run_one(dataclasses.asdict(bad))["status"] == "failed"
    changed = dataclasses.replace(good, timesteps=999)
    assert "other settings" in run_one(dataclasses.asdict(changed))["error"]


@pytest.fixture
def sigterm_is_harmless():
    """SIGTERM does nothing to this (test) process outside the code under test, which installs its own handler."""
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: None)
    yield
    signal.signal(signal.SIGTERM, previous)


@pytest.mark.timeout(300)
@pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals reach the main thread only")
def test_sigterm_while_a_worker_starts_stops_that_worker_too(tmp_path, monkeypatch, sigterm_is_harmless):
    """
    SIGTERM arriving just after a worker process has started, before the scheduler has recorded it (the window is
    wide on a first start: the forkserver imports torch first): that worker is stopped and collected like the others,
    its run is reported interrupted, and no process trains it once run_grid has returned.
    """
    import psutil

    from sb3_soup.experiments import parallel

    (spec,) = build_grid(
        "Pendulum-v1", tmp_path, models=["td3"], seeds=[0], timesteps=1_000_000, overrides=parse_overrides(FAST[:3])
    )
    started = []
    worker = parallel._Worker

    def signal_once_started(spec, process, connection):  # what LocalProcesses.submit records once the process runs
        started.append(process.pid)
        os.kill(os.getpid(), signal.SIGTERM)
        return worker(spec, process, connection)

    monkeypatch.setattr(parallel, "_Worker", signal_once_started)
    (result,) = run_grid([spec], workers=1, progress=False)
    assert result["status"] == "interrupted"
    (pid,) = started
    assert not psutil.pid_exists(pid) or psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    assert busy_reason(spec.run_dir) is None  # no process holds the run
    status_file = Path(spec.run_dir) / STATUS_FILE  # none when it stopped before its first step
    assert not status_file.exists() or json.loads(status_file.read_text())["status"] == "interrupted"


def test_a_run_being_trained_elsewhere_is_busy(tmp_path):
    (spec,) = build_grid(
        "Pendulum-v1", tmp_path, models=["td3"], seeds=[0], timesteps=100, overrides=parse_overrides(FAST[:3])
    )
    run_dir = Path(spec.run_dir)
    run_dir.mkdir(parents=True)
    with run_lock(run_dir):  # another process (here: another open file) holds the run
        assert "is being trained by pid" in busy_reason(run_dir)  # what the parent checks before starting a worker
        result = run_one(dataclasses.asdict(spec))
    assert result["status"] == "busy" and "is being trained by pid" in result["error"]
    assert busy_reason(run_dir) is None
    assert not (run_dir / ERROR_FILE).exists() and not (run_dir / "spec.json").exists()
    # A status that says running: the run is running while a process holds its lock, stalled (that process died) after
    (run_dir / STATUS_FILE).write_text(json.dumps({"status": "running", "step": 50, "total": 100, "time": time.time()}))
    write_grid(tmp_path, [spec])
    with run_lock(run_dir):
        assert [record.status for record in collect_runs(tmp_path)] == ["running"]
    assert [record.status for record in collect_runs(tmp_path)] == ["stalled"]
    assert run_one(dataclasses.asdict(spec))["status"] == "finished"
    assert is_finished(spec)


def test_progress_bars_in_a_terminal_and_lines_elsewhere(tmp_path):
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    specs = build_grid("Pendulum-v1", tmp_path, models=["td3"], seeds=[0, 1], timesteps=1000)
    assert progress_mode(True, Terminal()) == "bars" and progress_mode(True, io.StringIO()) == "lines"
    assert progress_mode(False, Terminal()) == "off"
    for spec in specs:
        Path(spec.run_dir).mkdir(parents=True)
    (Path(specs[0].run_dir) / STATUS_FILE).write_text(json.dumps({"status": "running", "step": 400, "total": 1000}))
    (Path(specs[1].run_dir) / CHECKPOINT_DIR).mkdir()
    (Path(specs[1].run_dir) / CHECKPOINT_DIR / "rl_model_300_steps.zip").touch()  # the step it will resume from

    terminal = Terminal()
    board = ProgressBoard(specs, "bars", stream=terminal)
    board.poll()
    board.finish(specs[1].key, {"status": "failed", "step": 0, "error": "boom"})
    board.close()
    screen = terminal.getvalue()
    assert "all 2 runs" in screen and "td3/seed_0" in screen and "td3/seed_1" in screen
    assert "400/1.00k" in screen and "1 running" in screen and "failed" in screen
    assert "300/1.00k" in screen and "300/2.00k" in screen  # the pending run's bar, and the overall one, start there

    log = io.StringIO()
    board = ProgressBoard(specs, "lines", stream=log, line_interval=0)
    board.poll()  # interval 0: a summary line at every poll
    board.finish(specs[1].key, {"status": "finished", "step": 1000})
    lines = log.getvalue().splitlines()
    assert lines[0].endswith("0/2 ended, 1 running; running: td3/seed_0 400/1000")
    assert lines[1] == "[1/2] td3/seed_1: finished at step 1000"
    assert "\r" not in log.getvalue()
    assert available_cores() >= 1


def test_end_to_end_interrupted_resumed_and_report(tmp_path, capsys):
    out = tmp_path / "runs"
    command = ["run", "--env", "Pendulum-v1", "--models", MODELS, "--heads", "2", "--seeds", "2", "--timesteps", "500",
               "--out", str(out), "--workers", "2", "--checkpoint-freq", "100", "--no-progress",
               "--hyperparams", *FAST]  # fmt: skip
    # 1. Interrupted: every run stops (resumably) after 250 steps, with a checkpoint.
    assert main([*command, "--stop-after", "250"]) == 2
    models = MODELS.split(",")
    run_dirs = sorted(path.parent for path in out.glob("*/seed_*/spec.json"))  # e.g. soup-k2/seed_0
    assert len(run_dirs) == 2 * len(models)
    first_session = {run_dir: json.loads((run_dir / STATUS_FILE).read_text())["wall_time_s"] for run_dir in run_dirs}
    for run_dir in run_dirs:
        latest = latest_checkpoint(run_dir / CHECKPOINT_DIR)
        assert latest is not None and latest.step == 250 and logs.count_episodes(run_dir) == 1
        assert not (run_dir / DONE_FILE).exists()
    assert {record.status for record in collect_runs(out)} == {"interrupted"}
    data = make_report(out)  # nothing finished yet: every run is listed as not included
    assert len(data["not_included"]) == 4 and "Not included (4 runs)" in (out / "table.md").read_text()

    # 2. Resumed: continues from step 250 and appends to the logs.
    assert main(command) == 0
    for run_dir in run_dirs:
        done = json.loads((run_dir / DONE_FILE).read_text())
        assert done["timesteps"] == 500
        # episodes end at 200 (first session), then 400 after the resume (the episode in progress at the checkpoint
        # goes on: the env's state is restored): two complete episodes, one header.
        assert logs.count_episodes(run_dir) == done["episodes"] == 2
        assert (run_dir / logs.MONITOR_FILE).read_text().count("r,l,t") == 1
        steps = logs.read_progress(run_dir)["time/total_timesteps"].tolist()
        assert steps == sorted(steps) and steps[-1] <= 500
        assert not (run_dir / CHECKPOINT_DIR).exists() and (run_dir / "model.zip").is_file()
        assert done["wall_time_s"] > first_session[run_dir] > 0  # the time spent training, in both sessions
    capsys.readouterr()
    assert main(command) == 0  # finished runs are skipped
    assert "4 skipped" in capsys.readouterr().out

    # 3. Report.
    assert main(["report", str(out), "--threshold", "-1400", "--speedup-threshold", "-1600", "--window", "1",
                 "--baseline", models[0]]) == 0  # fmt: skip
    for name in ("table.md", "metrics.json", "curves.png"):
        assert (out / name).is_file()
    data = json.loads((out / "metrics.json").read_text())
    assert data["not_included"] == [] and data["thresholds"]["Pendulum-v1"] == {"episode": -1400, "speed_up": -1600}
    labels = sorted({run_dir.parent.name for run_dir in run_dirs})  # the runs' labels, e.g. ddpg and soup-k2
    assert sorted(data["metrics"]["Pendulum-v1"]) == labels
    for label in labels:
        entry = data["metrics"]["Pendulum-v1"][label]
        returns = [logs.read_monitor(out / label / f"seed_{seed}")["r"].to_numpy() for seed in (0, 1)]
        assert entry["n_seeds"] == 2
        assert entry["avg_return"] == pytest.approx(np.mean([r.mean() for r in returns]))
        assert entry["max_return"] == pytest.approx(max(r.max() for r in returns))
    table = (out / "table.md").read_text()
    assert table.startswith("| Env. | Metric |") and "| Pendulum-v1 | Avg Return |" in table
    # the adaptive run logs its per-head confidence, drawn as Figure 6
    assert any(col.startswith("confidence/head_") for col in logs.read_progress(out / "soup-k2" / "seed_0").columns)
    assert (out / "confidence.png").is_file()

    # 4. Trap diagnostic on the trained runs. Pendulum's episodes all last 200 steps and end at 200 and 400: of the
    # windows (50, 150], (150, 250], (250, 350], (350, 450] after the 50 warm-up steps, the 2nd and 4th are trapped.
    assert main(["trap", str(out), "--lengths", "200-200", "--window", "100", "--eval-episodes", "1"]) == 0
    runs = json.loads((out / "trap.json").read_text())["runs"]
    assert len(runs) == 4
    for run in runs:
        assert (run["learning_steps"], run["steps_trapped"], run["last_trapped_step"]) == (400, 200, 450)
        assert 0.0 <= run["saturation"] <= 1.0


def test_confidence_suite_into_the_models_folder_trains_only_what_is_new(tmp_path, capsys):
    out = tmp_path / "runs"
    common = ["--env", "Pendulum-v1", "--heads", "2", "--seeds", "1", "--timesteps", "200", "--out", str(out),
              "--workers", "2", "--checkpoint-freq", "0", "--no-progress", "--hyperparams", *FAST]  # fmt: skip
    # The models suite's DBDDPG and SOUP, as an earlier `run --suite models` left them (trained here in-process).
    models = build_grid("Pendulum-v1", out, models=["dbddpg", "soup"], heads=[2], seeds=[0], timesteps=200,
                        overrides=parse_overrides(FAST), checkpoint_freq=0)  # fmt: skip
    write_grid(out, models, "models", [2])
    for spec in models:
        assert run_one(dataclasses.asdict(spec))["status"] == "finished"
    trained = {spec.key: (Path(spec.run_dir) / DONE_FILE).stat().st_mtime_ns for spec in models}

    capsys.readouterr()
    assert main(["run", "--suite", "confidence", *common]) == 0
    assert "Summary: 2 finished, 2 skipped" in capsys.readouterr().out
    assert sorted(path.name for path in out.iterdir() if path.is_dir()) == ["dbddpg-k2", "decayed-k2", "fixed-k2", "soup-k2"]
    assert {spec.key: (Path(spec.run_dir) / DONE_FILE).stat().st_mtime_ns for spec in models} == trained  # not retrained

    # The confidence suite's report: its columns and titles, Speed Up against "No confidence" (DBDDPG).
    assert main(["report", str(out), "--suite", "confidence", "--speedup-threshold", "-1500", "--window", "1"]) == 0
    report = out / "report-confidence"
    table = (report / "table.md").read_text()
    assert (
        "| No confidence (K=2) | Fixed confidence (K=2) | Decayed confidence (K=2) | Self-adaptive confidence (K=2) |" in table
    )
    assert _row(table, "Speed Up")[0] == "(baseline)"
    data = json.loads((report / "metrics.json").read_text())
    assert data["baseline"] == "dbddpg-k2" and data["columns"] == ["dbddpg-k2", "fixed-k2", "decayed-k2", "soup-k2"]
    assert data["not_included"] == [] and {"curves.png", "confidence.png"} <= set(data["files"])
    # The models suite's report from the same folder: only its models; its DDPG baseline is not there.
    assert main(["report", str(out), "--suite", "models"]) == 0
    table = (out / "report-models" / "table.md").read_text()
    assert table.splitlines()[2] == "| Env. | Metric | DBDDPG (K=2) | SOUP (K=2) |"
    assert "No Speed Up: its baseline `ddpg` is not in this folder" in table


@pytest.mark.slow
@pytest.mark.parametrize("how", ["ctrl-c", "kill"])
def test_ctrl_c_checkpoints_and_resumes(tmp_path, how):
    """
    A real SIGINT to the CLI and its workers (Ctrl-C in a terminal), or a SIGTERM to the CLI alone (`kill PID`, e.g. a
    command run in the background, which ignores SIGINT): the runs stop at a step, checkpoint, and resume to the end.
    """
    out = tmp_path / "runs"
    command = [sys.executable, "-m", "sb3_soup.experiments", "run", "--env", "Pendulum-v1", "--models", "td3",
               "--seeds", "1", "--timesteps", "3000", "--out", str(out), "--workers", "1", "--checkpoint-freq", "0",
               "--no-progress", "--hyperparams", *FAST]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen(command, env=env, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    status_file = out / "td3" / "seed_0" / "status.json"
    deadline = time.time() + 120
    while time.time() < deadline and not (status_file.is_file() and json.loads(status_file.read_text())["step"] > 200):
        time.sleep(0.2)
    if how == "ctrl-c":
        os.killpg(process.pid, signal.SIGINT)  # like Ctrl-C in a terminal: the CLI and its worker
    else:
        process.terminate()  # the CLI alone
    output = process.communicate(timeout=120)[0].decode()
    assert process.returncode == 2, output
    latest = latest_checkpoint(out / "td3" / "seed_0" / CHECKPOINT_DIR)
    assert latest is not None and 200 < latest.step < 3000
    finished = subprocess.run(command, env=env, capture_output=True, timeout=300)
    assert finished.returncode == 0, finished.stdout.decode() + finished.stderr.decode()
    assert json.loads((out / "td3" / "seed_0" / DONE_FILE).read_text())["timesteps"] == 3000


@pytest.mark.slow
def test_ray_backend_on_a_local_instance(tmp_path, capsys):
    """`run --ray-address local`: a private Ray instance runs the grid; a failing task does not stop the others."""
    pytest.importorskip("ray")
    out = tmp_path / "runs"
    command = ["run", "--env", "Pendulum-v1", "--models", "td3,sb3_ddpg", "--seeds", "1", "--timesteps", "250",
               "--out", str(out), "--workers", "2", "--no-progress", "--ray-address", "local",
               "--hyperparams", *FAST[:3], "sb3_ddpg:not_a_parameter=1"]  # fmt: skip
    assert main(command) == 1
    output = capsys.readouterr().out
    assert "Summary: 1 failed, 1 finished" in output and "FAILED sb3_ddpg/seed_0" in output and "not_a_parameter" in output
    assert (out / "td3" / "seed_0" / DONE_FILE).is_file()
    assert "not_a_parameter" in json.loads((out / "sb3_ddpg" / "seed_0" / ERROR_FILE).read_text())["traceback"]
    data = make_report(out, baseline="td3")
    assert data["not_included"] == ["Pendulum-v1:sb3_ddpg/seed_0"] and list(data["metrics"]["Pendulum-v1"]) == ["td3"]
    assert main(command) == 1  # again: the finished run is skipped without a task, the failing one fails again
    assert "1 skipped" in capsys.readouterr().out


def test_a_name_stores_one_variants_runs_under_it(tmp_path):
    specs = build_grid(
        "Pendulum-v1", tmp_path, models=["soup"], seeds=[0, 1], name="all-heads", overrides={"*": {"train_heads": "all"}}
    )
    assert {spec.model for spec in specs} == {"all-heads"} and {spec.label for spec in specs} == {"all-heads"}
    assert [spec.run_dir for spec in specs] == [str(tmp_path / "all-heads" / f"seed_{seed}") for seed in (0, 1)]
    assert all(spec.variant == "soup" and spec.hyperparams["train_heads"] == "all" for spec in specs)
    with pytest.raises(ValueError, match="stands for one model"):
        build_grid("Pendulum-v1", tmp_path, models=["soup", "dbddpg"], name="both")
    with pytest.raises(ValueError, match="folder name"):
        build_grid("Pendulum-v1", tmp_path, models=["soup"], name="a/b")


def test_a_named_run_is_its_own_column_in_a_suites_report_not_its_variants(tmp_path):
    def spec(**kwargs) -> RunSpec:
        return build_grid("Pendulum-v1", tmp_path, suite="benchmark", seeds=[0], **kwargs)[0]

    assert suite_columns(spec(models=["soup_defaults"]))["benchmark"] == ("soup_defaults", "SOUP (defaults)")
    named = spec(models=["soup_defaults"], name="qf_action0")
    assert suite_columns(named)["benchmark"] == ("soup_defaults", "qf_action0")
    # a variant stored as its twin (the paper's SOUP as the models suite's soup-k5) keeps the suite's title
    assert suite_columns(spec(models=["soup_paper"]))["benchmark"] == ("soup_paper", "SOUP, the paper's (K=5)")
