"""
The golden runs: every preset with both training schemes and every confidence strategy, a few hundred steps on
Pendulum-v1 with fixed seeds and every setting given explicitly (so that a change of defaults cannot move them).
``python tests/golden.py`` records their actions and parameter checksums in ``tests/data/golden.json``;
``tests/test_golden.py`` replays them. They were recorded before the redesign of the core (issue 13) and must stay
the same: a change that alters them is named and justified in its commit, and the file re-recorded.
"""

import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_soup import SOUP

GOLDEN_FILE = Path(__file__).parent / "data" / "golden.json"
STEPS = 300
# Every setting the paper mode uses, given explicitly
SETTINGS: dict[str, Any] = dict(
    n_heads=3,
    learning_rate=1e-4,
    critic_learning_rate=3e-4,
    buffer_size=10_000,
    learning_starts=100,
    batch_size=64,
    tau=1e-3,
    gamma=0.99,
    train_freq=1,
    gradient_steps=1,
    mask_prob=0.5,
    noise_std=0.2,
    noise_decay=0.999995,
    noise_std_min=0.05,
    alpha=0.5,
    decay=0.9995,
    temperature=1.0,
    temperature_mode="absolute",
    confidence_lr=1e-4,
    target_q="own",
    policy_delay=1,
    target_policy_noise=0.0,
    confidence_baseline=True,
    policy_kwargs=dict(net_arch=dict(pi_body=[256], pi_head=[128], qf_body=[256, 256], qf_head=[128])),
)
CASES: dict[str, dict[str, Any]] = {
    **{
        f"{preset}-{scheme}": dict(preset=preset, train_heads=scheme)
        for preset in ("ddpg", "ma_bddpg", "multi_ddpg", "dbddpg", "soup")
        for scheme in ("active", "all")
    },
    "fixed-active": dict(confidence="fixed", train_heads="active"),
    "decayed-active": dict(confidence="decayed", train_heads="active"),
}


class _Actions(BaseCallback):
    def __init__(self) -> None:
        super().__init__()
        self.actions: list[np.ndarray] = []

    def _on_step(self) -> bool:
        self.actions.append(np.array(self.locals["actions"], dtype=np.float64).copy())
        return True


def run_case(name: str) -> dict[str, Any]:
    """Train one case and return its actions and the checksum of its parameters."""
    th.set_num_threads(1)
    model = SOUP("MlpPolicy", "Pendulum-v1", seed=0, device="cpu", **SETTINGS, **CASES[name])
    recorder = _Actions()
    model.learn(STEPS, callback=recorder)
    parameters = th.cat([p.detach().double().flatten() for p in model.policy.state_dict().values() if p.is_floating_point()])
    return {
        "actions": np.concatenate(recorder.actions).ravel().tolist(),
        "parameter_sum": float(parameters.sum()),
        "parameter_abs_sum": float(parameters.abs().sum()),
        "parameter_sha256": hashlib.sha256(parameters.numpy().tobytes()).hexdigest(),
    }


if __name__ == "__main__":
    cases = sys.argv[1:] or list(CASES)
    golden = json.loads(GOLDEN_FILE.read_text()) if GOLDEN_FILE.exists() else {}
    golden.update({name: run_case(name) for name in cases})
    GOLDEN_FILE.write_text(json.dumps(golden, indent=1, sort_keys=True) + "\n")
    print(f"recorded {cases} in {GOLDEN_FILE}")
