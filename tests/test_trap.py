"""
Tests of the trap diagnostic (``python -m sb3_soup.experiments trap``): the window arithmetic on hand-made episode
lengths, the saturation of a model's actions, and the report over a folder of hand-made runs.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from sb3_soup.experiments import logs
from sb3_soup.experiments.__main__ import main
from sb3_soup.experiments.grid import build_grid
from sb3_soup.experiments.report import write_grid
from sb3_soup.experiments.runner import DONE_FILE, STATUS_FILE
from sb3_soup.experiments.trap import action_saturation, trap_report, trapped_windows


def test_trapped_windows_hand_made():
    # warm-up of 100 steps, windows of 100: (100, 200], (200, 300], (300, 400], (400, 500]
    lengths = [50, 50]  # end at 50, 100: warm-up, not counted
    lengths += [22] * 4 + [12]  # end in (100, 200]: 4 of 5 trap episodes = 80%
    lengths += [22] * 4  # ends at 188 + 22k: 210, 232, 254, 276 -> (200, 300] all trap
    lengths += [200]  # ends at 476: the only episode of (400, 500], not a trap; (300, 400] has no episode
    trapped = trapped_windows(lengths, start=100, end=500, window=100, trap_lengths=(21, 24), fraction=0.9)
    assert trapped.tolist() == [False, True, False, False]
    # 80% is above a fraction of 0.75: the first window is trapped too
    assert trapped_windows(lengths, 100, 500, 100, (21, 24), 0.75).tolist() == [True, True, False, False]
    # only whole windows: a run that stopped at 450 has three
    assert trapped_windows(lengths, 100, 450, 100, (21, 24), 0.9).tolist() == [False, True, False]
    assert trapped_windows([], 100, 50, 100).tolist() == []


class _ConstantModel:
    """Acts with the same action everywhere; ``policy.scale_action`` maps Pendulum's [-2, 2] to [-1, 1]."""

    def __init__(self, action: float):
        self.action = np.array([action], dtype=np.float32)
        self.policy = SimpleNamespace(scale_action=lambda action: action / 2.0)

    def predict(self, obs, deterministic=False):
        assert deterministic
        return self.action, None


def test_action_saturation_counts_components_beyond_the_bound():
    assert action_saturation(_ConstantModel(2.0), "Pendulum-v1", episodes=1) == 1.0
    assert action_saturation(_ConstantModel(-1.99), "Pendulum-v1", episodes=1) == 1.0  # 0.995 > 0.99
    assert action_saturation(_ConstantModel(1.0), "Pendulum-v1", episodes=1) == 0.0
    assert action_saturation(_ConstantModel(1.0), "Pendulum-v1", episodes=1, bound=0.4) == 1.0


def _hand_made_run(spec, lengths, finished: bool = True) -> None:
    run_dir = Path(spec.run_dir)
    run_dir.mkdir(parents=True)
    (run_dir / "spec.json").write_text(spec.to_json())
    rows = "".join(f"{39.0 if 21 <= length <= 24 else 100.0},{length},0.0\n" for length in lengths)
    (run_dir / logs.MONITOR_FILE).write_text('#{"t_start": 0, "env_id": "Hopper-v4"}\nr,l,t\n' + rows)
    step = int(sum(lengths))
    state = "finished" if finished else "interrupted"
    status = {"status": state, "step": step, "total": spec.timesteps, "time": time.time()}
    (run_dir / STATUS_FILE).write_text(json.dumps(status))
    if finished:
        (run_dir / DONE_FILE).write_text(json.dumps({"timesteps": step, "episodes": len(lengths)}))


def test_trap_report_on_hand_made_runs(tmp_path, capsys):
    out = tmp_path / "hopper"
    specs = build_grid(
        "Hopper-v4", out, models=["ddpg", "soup"], heads=[2], seeds=[0, 1], timesteps=3000,
        overrides={"*": {"learning_starts": 1000}},
    )  # fmt: skip
    write_grid(out, specs, "models", [2])
    runs = {spec.key: spec for spec in specs}
    _hand_made_run(runs["ddpg/seed_0"], [100] * 10 + [22] * 50 + [100] * 9)  # 1000 warm-up, (1000, 2000] trapped
    _hand_made_run(runs["ddpg/seed_1"], [100] * 30)  # never trapped
    _hand_made_run(runs["soup-k2/seed_0"], [100] * 10 + [22] * 91)  # 3002 steps: two whole windows, trapped
    _hand_made_run(runs["soup-k2/seed_1"], [100] * 15, finished=False)

    assert main(["trap", str(out), "--suite", "models", "--eval-episodes", "0"]) == 0
    printed = capsys.readouterr().out
    # ddpg seed 0 ends with 9 episodes of return 100 after step 2100 (of 3000, > the last 20%'s start, 2400: 6 of them)
    assert "| DDPG | 0 / 1 | 1k / 0k (of 2k) | 2k / - | - / - | 100 / 100 |" in printed
    assert "| SOUP (K=2) | 0 | 2k (of 2k) | 3k | - | 39 |" in printed
    assert "soup-k2/seed_1 (interrupted)" in printed
    data = json.loads((out / "report-models" / "trap.json").read_text())
    settings = {"window": 1000, "lengths": [21, 24], "fraction": 0.9, "eval_episodes": 0, "final_fraction": 0.2}
    assert data["settings"] == settings
    ddpg_0 = next(run for run in data["runs"] if run["model"] == "ddpg" and run["seed"] == 0)
    assert ddpg_0["steps_trapped"] == 1000 and ddpg_0["trap_return"] == pytest.approx(39.0)
    assert (out / "report-models" / "trap.md").read_text() in printed

    # longer trap lengths: every window of ddpg seed 1 counts
    _, results, skipped = trap_report(out, window=500, trap_lengths=(100, 100), eval_episodes=0, report_dir=tmp_path)
    assert {(r.model, r.seed): r.steps_trapped for r in results}[("ddpg", 1)] == 2000
    assert skipped == ["soup-k2/seed_1 (interrupted)"]
    # the last half of ddpg seed 0 (steps > 1500): 28 trap episodes (return 39) end at 1522..2100, then 9 of 100
    _, results, _ = trap_report(out, eval_episodes=0, report_dir=tmp_path, final_fraction=0.5)
    assert {(r.model, r.seed): r.final_return for r in results}[("ddpg", 0)] == pytest.approx((28 * 39 + 9 * 100) / 37)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--lengths", "24"], "SHORTEST-LONGEST"),
        (["--lengths", "a-b"], "SHORTEST-LONGEST"),
    ],
)
def test_trap_bad_lengths(tmp_path, argv, message, capsys):
    with pytest.raises(SystemExit):
        main(["trap", str(tmp_path), *argv])
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"window": 0}, "window"),
        ({"fraction": 1.0}, "fraction"),
        ({"trap_lengths": (24, 21)}, "lengths"),
        ({"final_fraction": 0.0}, "final_fraction"),
    ],
)
def test_trap_bad_settings(tmp_path, kwargs, message):
    with pytest.raises(ValueError, match=message):
        trap_report(tmp_path, **kwargs)


def test_a_run_without_learning_starts_uses_its_algorithms_default(tmp_path):
    spec = build_grid("Hopper-v4", tmp_path, models=["soup"], heads=[2], seeds=[0], timesteps=3000)[0]
    spec.hyperparams.pop("learning_starts", None)
    _hand_made_run(spec, [100] * 30)
    _, results, _ = trap_report(tmp_path, window=500, eval_episodes=0, trap_lengths=(100, 100))
    # SOUP's default warm-up is SB3's 100 steps: five whole windows of 500 after it (a 1000-step warm-up would give four)
    assert (results[0].learning_steps, results[0].steps_trapped) == (2500, 2500)
