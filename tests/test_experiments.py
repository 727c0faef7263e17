"""Tests of the experiment runner (sb3_soup.experiments): grid, metrics, checkpoints, logs, run/resume, report."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sb3_soup.experiments import checkpointing, logs
from sb3_soup.experiments.__main__ import main
from sb3_soup.experiments.grid import VARIANTS, build_grid, load_hyperparams, parse_overrides, parse_seeds
from sb3_soup.experiments.metrics import add_speed_ups, first_crossing, model_metrics, running_average, speed_up
from sb3_soup.experiments.parallel import run_local
from sb3_soup.experiments.report import collect_runs, make_report
from sb3_soup.experiments.runner import DONE_FILE, ERROR_FILE, run_one

try:
    from sb3_soup import SOUP  # type: ignore[attr-defined]  # noqa: F401

    HAS_SOUP = True
except ImportError:
    HAS_SOUP = False

# Two cheap models: SOUP's DDPG preset and SOUP once the core algorithm is there, SB3's TD3/DDPG until then.
MODELS = "ddpg,soup" if HAS_SOUP else "td3,sb3_ddpg"
FAST = ["learning_starts=50", "batch_size=32", "buffer_size=5000", "policy_kwargs=dict(net_arch=[32, 32])"]
if HAS_SOUP:
    FAST.append("policy_kwargs=dict(net_arch=dict(pi_body=[32], pi_head=[16], qf_body=[32, 32], qf_head=[16]))")


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


# ---------------------------------------------------------------- grid and hyper-parameters


def test_grid_suites_and_overrides(tmp_path):
    specs = build_grid("Pendulum-v1", tmp_path, suite="models", seeds=[0, 1], timesteps=100)
    assert [spec.model for spec in specs[::2]] == ["ddpg", "ma_bddpg-k5", "multi_ddpg-k5", "dbddpg-k5", "soup-k5", "td3"]
    assert specs[2].hyperparams["preset"] == "ma_bddpg" and specs[2].hyperparams["n_heads"] == 5
    assert "n_heads" not in specs[0].hyperparams and specs[0].hyperparams["preset"] == "ddpg"
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
    assert parse_seeds("3") == [0, 1, 2] and parse_seeds("4,7") == [4, 7]
    with pytest.raises(ValueError, match="Unknown model"):
        build_grid("Pendulum-v1", tmp_path, models=["nope"])
    assert set(VARIANTS) >= {"ddpg", "ma_bddpg", "multi_ddpg", "dbddpg", "soup", "td3", "none", "fixed", "decayed", "adaptive"}


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


# ---------------------------------------------------------------- checkpoints and logs


def test_checkpoint_roundtrip(tmp_path):
    import gymnasium as gym
    from stable_baselines3 import TD3
    from stable_baselines3.common.vec_env import DummyVecEnv

    env = DummyVecEnv([lambda: logs.monitor_env(gym.make("Pendulum-v1"), tmp_path)])
    model = TD3("MlpPolicy", env, learning_starts=20, batch_size=16, policy_kwargs={"net_arch": [16]}, seed=0)
    model.learn(60)
    assert checkpointing.latest_checkpoint(tmp_path) is None
    first = checkpointing.save_checkpoint(model, tmp_path, {"episodes": 0})
    model.learn(40, reset_num_timesteps=False)
    second = checkpointing.save_checkpoint(model, tmp_path, {"episodes": 0})
    latest = checkpointing.latest_checkpoint(tmp_path)
    assert latest is not None and latest.step == second.step == 100 and not first.path.exists()
    assert latest.state == {"episodes": 0, "num_timesteps": 100}
    resumed = checkpointing.resume(latest, TD3, env)
    assert resumed.num_timesteps == 100 and resumed.replay_buffer.size() == 100
    assert checkpointing.remaining_steps(resumed, 150) == 50
    resumed.learn(checkpointing.remaining_steps(resumed, 150), reset_num_timesteps=False)
    assert resumed.num_timesteps == 150
    env.close()


def test_logs_continue_after_truncation(tmp_path):
    (tmp_path / logs.MONITOR_FILE).write_text('#{"t_start": 0}\nr,l,t\n1.0,10,0.1\n2.0,10,0.2\n3.0,10,0.3\n')
    logs.truncate_monitor(tmp_path, 2)
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


def test_failing_run_is_reported_and_others_finish(tmp_path):
    good, bad = build_grid(
        "Pendulum-v1", tmp_path, models=["td3", "sb3_ddpg"], seeds=[0], timesteps=120, overrides=parse_overrides(FAST[:3])
    )
    bad = dataclasses.replace(bad, hyperparams={**bad.hyperparams, "not_a_parameter": 1})
    results = run_local([good, bad], workers=2, progress=False)
    assert [result["status"] for result in results] == ["finished", "failed"]
    assert "not_a_parameter" in results[1]["error"]
    assert "not_a_parameter" in json.loads((Path(bad.run_dir) / ERROR_FILE).read_text())["traceback"]
    assert (Path(good.run_dir) / DONE_FILE).is_file()
    # The same spec run again in-process fails the same way, and its folder keeps refusing other settings.
    assert run_one(dataclasses.asdict(bad))["status"] == "failed"
    changed = dataclasses.replace(good, timesteps=999)
    assert "other settings" in run_one(dataclasses.asdict(changed))["error"]


def test_end_to_end_interrupted_resumed_and_report(tmp_path, capsys):
    out = tmp_path / "runs"
    command = ["run", "--env", "Pendulum-v1", "--models", MODELS, "--seeds", "2", "--timesteps", "500", "--out", str(out),
               "--workers", "2", "--checkpoint-freq", "100", "--no-progress", "--hyperparams", *FAST]  # fmt: skip
    # 1. Interrupted: every run stops (resumably) after 250 steps, with a checkpoint.
    assert main([*command, "--stop-after", "250"]) == 2
    models = MODELS.split(",")
    run_dirs = sorted(path.parent for path in out.glob("*/seed_*/spec.json"))  # e.g. soup-k5/seed_0
    assert len(run_dirs) == 2 * len(models)
    for run_dir in run_dirs:
        latest = checkpointing.latest_checkpoint(run_dir)
        assert latest is not None and latest.step == 250 and latest.state["episodes"] == 1
        assert not (run_dir / DONE_FILE).exists()
    assert {record.status for record in collect_runs(out)} == {"interrupted"}
    data = make_report(out)  # nothing finished yet: every run is listed as not included
    assert len(data["not_included"]) == 4 and "Not included (4 runs)" in (out / "table.md").read_text()

    # 2. Resumed: continues from step 250 and appends to the logs.
    assert main(command) == 0
    for run_dir in run_dirs:
        done = json.loads((run_dir / DONE_FILE).read_text())
        assert done["timesteps"] == 500
        # episodes end at 200 (first session), then 250 + 200 = 450 after the resume (the episode in progress at the
        # checkpoint is abandoned): two complete episodes, one header.
        assert logs.count_episodes(run_dir) == done["episodes"] == 2
        assert (run_dir / logs.MONITOR_FILE).read_text().count("r,l,t") == 1
        steps = logs.read_progress(run_dir)["time/total_timesteps"].tolist()
        assert steps == sorted(steps) and steps[-1] <= 500
        assert not (run_dir / checkpointing.CHECKPOINT_DIR).exists() and (run_dir / "model.zip").is_file()
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
    labels = sorted({run_dir.parent.name for run_dir in run_dirs})  # the runs' labels, e.g. ddpg and soup-k5
    assert sorted(data["metrics"]["Pendulum-v1"]) == labels
    for label in labels:
        entry = data["metrics"]["Pendulum-v1"][label]
        returns = [logs.read_monitor(out / label / f"seed_{seed}")["r"].to_numpy() for seed in (0, 1)]
        assert entry["n_seeds"] == 2
        assert entry["avg_return"] == pytest.approx(np.mean([r.mean() for r in returns]))
        assert entry["max_return"] == pytest.approx(max(r.max() for r in returns))
    table = (out / "table.md").read_text()
    assert table.startswith("| Env. | Metric |") and "| Pendulum-v1 | Avg Return |" in table
    if HAS_SOUP:  # the adaptive run logs its per-head confidence, drawn as Figure 6
        assert any(col.startswith("confidence/head_") for col in logs.read_progress(out / "soup-k5" / "seed_0").columns)
        assert (out / "confidence.png").is_file()


@pytest.mark.slow
def test_ctrl_c_checkpoints_and_resumes(tmp_path):
    """A real SIGINT to the CLI (and its workers): the runs stop at a step, checkpoint, and resume to the end."""
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
    os.killpg(process.pid, signal.SIGINT)  # like Ctrl-C in a terminal: the CLI and its worker
    output = process.communicate(timeout=120)[0].decode()
    assert process.returncode == 2, output
    latest = checkpointing.latest_checkpoint(out / "td3" / "seed_0")
    assert latest is not None and 200 < latest.step < 3000
    finished = subprocess.run(command, env=env, capture_output=True, timeout=300)
    assert finished.returncode == 0, finished.stdout.decode() + finished.stderr.decode()
    assert json.loads((out / "td3" / "seed_0" / DONE_FILE).read_text())["timesteps"] == 3000


@pytest.mark.slow
def test_ray_backend_local(tmp_path):
    pytest.importorskip("ray")
    from sb3_soup.experiments.parallel import run_ray

    specs = build_grid(
        "Pendulum-v1", tmp_path, models=["td3"], seeds=[0, 1], timesteps=150, overrides=parse_overrides(FAST[:3])
    )
    results = run_ray(specs, "local", progress=False)
    assert [result["status"] for result in results] == ["finished", "finished"]
    assert all((Path(spec.run_dir) / DONE_FILE).is_file() for spec in specs)
    assert make_report(tmp_path)["not_included"] == []
