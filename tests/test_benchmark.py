"""
The throughput benchmark's plumbing (benchmarks/throughput.py): not timed, speed targets live in the benchmark itself.
"""

import json
import pathlib
import subprocess
import sys

import pytest
from scripts import load_script

from sb3_soup.policies import DEFAULT_ACTION_LAYER
from sb3_soup.presets import PAPER_UPDATE

SCRIPT = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "throughput.py"


def load_benchmark():
    return load_script("benchmarks/throughput.py")


def test_flop_counts():
    bench = load_benchmark()
    ddpg = dict(algo="ddpg", batch_size=1024)
    soup = dict(algo="soup", batch_size=1024, n_heads=10, train_heads="all", confidence="adaptive")
    # DDPG [256, 256] on Hopper: about 0.76M multiply-adds per sample and update
    assert bench.train_flops(ddpg) == pytest.approx(2 * 1024 * 762_000, rel=0.01)
    # all heads at K=10: about 5x DDPG's arithmetic with the paper's critic (the body's observation part once), 7x with
    # the action at the critic's input (the body runs once per head's action); the active pair about DDPG's
    assert bench.SOUP_ACTION_LAYER == DEFAULT_ACTION_LAYER == 1  # the script's copy (a --before checkout's may differ)
    assert 4.5 < bench.train_flops(soup) / bench.train_flops(ddpg) < 5.5
    active = dict(soup, train_heads="active")
    assert 0.9 < bench.train_flops(active) / bench.train_flops(ddpg) < 1.1
    assert 6.7 < bench.train_flops(soup, action_layer=0) / bench.train_flops(ddpg) < 7.7
    assert 0.9 < bench.train_flops(active, action_layer=0) / bench.train_flops(ddpg) < 1.1
    # FLOPs scale with the batch
    assert bench.train_flops(dict(ddpg, batch_size=256)) == pytest.approx(bench.train_flops(ddpg) / 4)
    # predict: the E-Critic scores K x K (candidate, critic head) pairs
    assert bench.predict_flops(soup) / bench.predict_flops(ddpg) > 40
    names = [bench.config_name(c) for c in bench.make_configs(quick=False, batch_sizes=[1024, 256])]
    assert len(names) == len(set(names)) == 2 * (3 + 1 + 3 * 2 * 2)  # DDPG, TD3 twice, the defaults, the grid
    # the scheme's savings: a delayed actor, all critics with one actor head; a second target head costs a little
    all_pairs = dict(soup, n_heads=5, batch_size=256)
    cheaper = dict(all_pairs, defaults=True)
    paper = bench.PAPER_SCHEME
    assert paper == PAPER_UPDATE  # the script's copy (a --before checkout may lack the constant)
    bench.soup_defaults = lambda: dict(paper, train_heads="all", policy_delay=2, confidence="adaptive")
    assert 0.7 < bench.train_flops(cheaper) / bench.train_flops(all_pairs) < 0.8  # actor every other update
    bench.soup_defaults = lambda: dict(paper, train_heads="all", target_q="min_pair", confidence="adaptive")
    assert 1.0 < bench.train_flops(cheaper) / bench.train_flops(all_pairs) < 1.2  # one more head per target
    bench.soup_defaults = lambda: dict(paper, train_heads="all_critics", confidence="adaptive")
    assert bench.train_flops(cheaper) / bench.train_flops(all_pairs) < 0.8  # one actor head per update


def test_quick_mode_writes_the_table(tmp_path):
    # about 15 s: four short child processes (not timed: it checks the JSON, not the speed)
    out = tmp_path / "quick.json"
    command = [sys.executable, str(SCRIPT), "--quick", "--window", "0.5", "--learning-starts", "64"]
    command += ["--memory-buffer", "5000", "--only", "K=10 active adaptive", "--out", str(out)]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "x DDPG" in done.stdout
    results = json.loads(out.read_text())
    assert results["meta"]["env"] == "Hopper-v4" and results["meta"]["repeats"] == 1
    speed_rows = [row for row in results["rows"] if "steps_per_s" in row]
    assert {row["name"] for row in speed_rows} == {"ddpg b1024", "soup K=10 active adaptive b1024"}
    for row in speed_rows:
        for key in ("steps_per_s", "predict_1_ms", "predict_8_ms", "train_gflop", "speed_ratio", "flop_ratio"):
            assert row[key] > 0, key
        # where an env-step's time goes: acting and the gradient step are parts of it, eq. 8's update a part of the latter
        assert 0 < row["act_ms"] + row["train_ms"] < row["step_ms"]
        assert row["step_ms"] == pytest.approx(1e3 / row["steps_per_s"], rel=0.05)
        # one thread: the process's CPU time over the window is at most its wall time (less where others took the core)
        assert row["cpu_steps_per_s"] >= 0.95 * row["steps_per_s"]
    ddpg, soup = sorted(speed_rows, key=lambda row: row["name"])
    assert ddpg["confidence_ms"] == 0 < soup["confidence_ms"] < soup["train_ms"]
    assert "ms per env-step" in done.stdout
    memory_rows = [row for row in results["rows"] if "peak_rss_mb" in row]
    assert len(memory_rows) == 2
    soup_memory = next(row for row in memory_rows if row["name"].startswith("soup"))
    assert soup_memory["mask_dtype"] == "bool" and soup_memory["peak_rss_mb"] > 0


def test_a_named_scheme_is_a_row_of_soups_defaults_with_its_settings():
    bench = load_benchmark()
    name, settings = bench.parse_scheme("crit-redq:train_heads=all_critics,target_q=redq,target_policy_noise=0.2")
    assert (name, settings) == ("crit-redq", dict(train_heads="all_critics", target_q="redq", target_policy_noise=0.2))
    configs = bench.make_configs(quick=True, batch_sizes=[256], schemes=[(name, settings)])
    row = next(c for c in configs if c.get("scheme"))
    assert bench.config_name(row) == "soup K=5 crit-redq b256"
    assert bench.scheme(row) == {**bench.soup_defaults(), **settings}
    # REDQ's target reads two target heads per pair, as min_pair does
    min_pair = dict(row, scheme=dict(settings, target_q="min_pair"))
    assert (
        bench.train_flops(row)
        == bench.train_flops(min_pair)
        > bench.train_flops(dict(row, scheme=dict(settings, target_q="own")))
    )
    with pytest.raises(Exception, match="NAME:key=value"):
        bench.parse_scheme("no-settings")


def test_the_screens_candidates_are_schemes_but_those_that_set_the_networks(capsys):
    bench = load_benchmark()
    path = pathlib.Path(__file__).resolve().parents[1] / "docs" / "results" / "screen" / "candidates.yml"
    schemes = dict(bench.read_schemes(str(path), None))
    assert "soup_crit_redq_s_d2" in schemes and "soup_layer_norm" not in schemes
    assert "not measured: soup_layer_norm (policy_kwargs)" in capsys.readouterr().err
    configs = bench.make_configs(quick=True, batch_sizes=[256], schemes=list(schemes.items()))
    names = {bench.config_name(c): c for c in configs}
    assert names["soup K=10 soup_k10 b256"]["n_heads"] == 10  # n_heads sets K
    assert bench.scheme(names["soup K=5 soup_mask1 b256"])["mask_prob"] == 1.0
    # values with commas inside brackets stay whole; networks are refused
    assert bench.parse_scheme("a:n_heads=3,x=[1, 2]") == ("a", dict(n_heads=3, x=[1, 2]))
    with pytest.raises(Exception, match="policy_kwargs are not measured"):
        bench.parse_scheme("a:policy_kwargs=dict(layer_norm=True)")
