"""
The golden runs: every preset with both training schemes and every confidence strategy, a few hundred steps on
Pendulum-v1 with fixed seeds and every setting given explicitly (so that a change of defaults cannot move them).
They were recorded before the redesign of the core (issue 13) and must stay the same: a change that alters them is
named and justified in its commit, and the file re-recorded. ``tests/test_golden.py`` replays them.

What a run records (:func:`run_case`): the actions it took, the bootstrap masks it drew, after the warm-up every
actor head's candidate, its E-Q value and the head chosen, every value that ``train`` logs (the losses of every
update, ...) and how far training moved each network's body and each of its heads. Not the bits of the parameters:
another CPU, another BLAS path or another torch rounds differently, and training amplifies that (issue 21), so the
test compares at tolerances measured across such settings (see ``tests/test_golden.py``).

Re-record (all cases, or the ones named), from the repository's root, after a change meant to alter the runs (named
and justified in its commit; see first with ``--compare`` how far it moved them)::

    python tests/golden.py [CASE ...]

Measure how far a setting moves the runs from the recorded ones: for each case the horizon (how many steps after the
warm-up the test compares) and, for each quantity, its largest deviation relative to its scale in the first
``TIGHT_STEPS`` steps and in the rest (compare with the test's ``TIGHT`` and ``LOOSE``). Proxies for another machine:
torch's kernels for another CPU (``ATEN_CPU_CAPABILITY=default``, or ``avx512`` where the CPU has it), MKL's code
paths (``MKL_CBWR=COMPATIBLE``, ``AVX``...), torch threads::

    ATEN_CPU_CAPABILITY=default python tests/golden.py --compare
    MKL_CBWR=COMPATIBLE python tests/golden.py --compare --threads 2 --save runs.json
"""

import argparse
import json
import sys
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_soup import SOUP, DecayingNormalActionNoise

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
    target_q="own",
    policy_delay=1,
    target_policy_noise=0.0,
    policy_kwargs=dict(net_arch=dict(pi_body=[256], pi_head=[128], qf_body=[256, 256], qf_head=[128], qf_action_layer=1)),
)
WARMUP = SETTINGS["learning_starts"]  # the first steps act at random: no network is involved
# The paper mode's noise, std 0.2 decayed by 0.999995 per step down to 0.05, as the runs were recorded (before issue 20):
# its schedule then counted the warm-up's steps too, so the first noisy step's std was 0.2 * 0.999995 ** WARMUP. A
# DecayingNormalActionNoise counts its draws, none during the warm-up: it starts from there and draws the same numbers.
NOISE = dict(sigma=0.2 * 0.999995**WARMUP, decay=0.999995, sigma_min=0.05)
# Every argument of each strategy (the no-confidence presets have none)
ADAPTIVE = dict(lr=1e-4, temperature=1.0, temperature_mode="absolute", baseline=True)
CASES: dict[str, dict[str, Any]] = {
    **{
        f"{preset}-{scheme}": dict(
            preset=preset, train_heads=scheme, **({"confidence_kwargs": ADAPTIVE} if preset == "soup" else {})
        )
        for preset in ("ddpg", "ma_bddpg", "multi_ddpg", "dbddpg", "soup")
        for scheme in ("active", "all")
    },
    "fixed-active": dict(confidence="fixed", confidence_kwargs=dict(alpha=0.5), train_heads="active"),
    "decayed-active": dict(confidence="decayed", confidence_kwargs=dict(decay=0.9995), train_heads="active"),
}
ACTION_BOUND = 2.0  # Pendulum-v1's largest torque: the scale of its actions


class _Recorder(BaseCallback):
    """The actions taken and, after the warm-up, what the ensemble chose them from (with more than one actor head)."""

    def __init__(self) -> None:
        super().__init__()
        self.actions: list[np.ndarray] = []
        self.chosen: list[int] = []
        self.e_q: list[list[float]] = []
        self.candidates: list[list[float]] = []

    def _on_step(self) -> bool:
        self.actions.append(np.array(self.locals["actions"], dtype=np.float64).copy())
        step = self.model.num_timesteps - 1  # the env step just taken, from self.model._last_obs
        if step >= WARMUP and self.model.policy.n_actor_heads > 1:
            view = self.model.policy.ensemble_view(self.model._last_obs, explore=True)  # what the step acted on
            self.chosen.append(int(view.chosen[0]))
            self.e_q.append(view.e_q[0].astype(np.float64).tolist())
            self.candidates.append(view.candidates[0].astype(np.float64).ravel().tolist())
        return True


def _parts(model: SOUP) -> dict[str, th.Tensor]:
    """
    The policy's floating-point parameters and buffers in parts, flattened in float64: each network's shared part
    (``actor.body``, ...), each of its heads (``critic.head1``: the head's slice of the batched head layers) and the
    confidence strategy (``confidence``).
    """
    parts: dict[str, list[th.Tensor]] = defaultdict(list)
    for key, value in model.policy.state_dict().items():
        if not value.is_floating_point():
            continue
        network = key.split(".")[0]
        value = value.detach().double()
        if network != "confidence" and ".heads." in key:  # (K, in, out) weights and (K, 1, out) biases
            for head, rows in enumerate(value):
                parts[f"{network}.head{head}"].append(rows.flatten())
        else:
            parts[network if network == "confidence" else f"{network}.body"].append(value.flatten())
    return {name: th.cat(values) for name, values in parts.items()}


def run_case(name: str, steps: int = STEPS, threads: int = 1) -> dict[str, Any]:
    """
    Train one case and return what it did.

    :param name: a key of :data:`CASES`
    :param steps: env steps to train
    :param threads: torch's intra-op threads (the recording and the test use 1; more to measure their effect)
    :return: ``actions`` (every env step's), ``masks`` (each transition's bootstrap mask, as a string of 0/1),
        ``chosen``, ``e_q`` and ``candidates`` (for each step after the warm-up, with several actor heads: the head
        whose action was taken, each candidate's E-Q value and each candidate's action before the noise), ``updates``
        (each value ``train`` logs, a list over the updates: update ``t`` follows step ``WARMUP + t``) and ``moved``
        (for each part of :func:`_parts`, ``sum |theta - theta_0|`` over the run)
    """
    th.set_num_threads(threads)
    noise = DecayingNormalActionNoise(np.zeros(1), np.full(1, NOISE["sigma"]), NOISE["decay"], NOISE["sigma_min"])
    model = SOUP("MlpPolicy", "Pendulum-v1", seed=0, device="cpu", action_noise=noise, **SETTINGS, **CASES[name])
    initial = _parts(model)
    updates: dict[str, list[float]] = defaultdict(list)
    train = model.train

    def recording_train(gradient_steps: int, batch_size: int = 64) -> None:
        train(gradient_steps, batch_size)
        logged = model.logger.name_to_value
        for key in [key for key in logged if key.startswith("train/")]:  # taken out: the next update logs its own
            updates[key.removeprefix("train/")].append(float(logged.pop(key)))

    model.train = recording_train  # type: ignore[method-assign]
    recorder = _Recorder()
    model.learn(steps, callback=recorder)
    final = _parts(model)
    masks = model.replay_buffer.masks[: model.replay_buffer.size(), 0]  # type: ignore[union-attr]
    return {
        "actions": np.concatenate(recorder.actions).ravel().tolist(),
        "masks": ["".join(str(int(bit)) for bit in row) for row in masks],
        "chosen": recorder.chosen,
        "e_q": recorder.e_q,
        "candidates": recorder.candidates,
        "updates": dict(updates),
        "moved": {part: float((final[part] - initial[part]).abs().sum()) for part in final},
    }


def horizon(record: dict[str, Any], tolerance: Callable[[int], float]) -> int:
    """
    How many steps after the warm-up another machine takes the recorded actions, given that its values may differ
    from the recorded ones by ``tolerance(t)`` at step ``t`` (relative to their scale): up to the first step whose
    choice such differences could change, that is where the chosen candidate's E-Q value leads another's by at most
    ``2 * tolerance(t)`` (both may move, in opposite directions) and the other's action differs by more than
    ``tolerance(t)``. From there on the runs may part (a tie between candidates of the same action is no such step).

    :param record: a run of :func:`run_case`
    :param tolerance: the relative tolerance at each step after the warm-up
    :return: the number of steps after the warm-up (and updates) that can be compared
    """
    for t, (chosen, e_q, candidates) in enumerate(zip(record["chosen"], record["e_q"], record["candidates"])):
        e_q, tol = np.asarray(e_q), tolerance(t)
        candidates = np.asarray(candidates).reshape(len(e_q), -1)  # (Ka, A)
        close = e_q[chosen] - e_q <= 2 * tol * np.abs(e_q).max()
        apart = np.abs(candidates - candidates[chosen]).max(axis=1) > tol * ACTION_BOUND
        if (close & apart).any():
            return t
    return len(record["actions"]) - WARMUP


def deviation(got: dict[str, Any], expected: dict[str, Any], quantity: str, steps: slice) -> float:
    """
    The largest difference of one quantity between two runs over some steps after the warm-up, relative to its scale.

    :param quantity: ``"actions"`` and ``"candidates"`` (relative to :data:`ACTION_BOUND`), ``"e_q"`` (to each step's
        largest E-Q value), or ``"updates/KEY"`` (a value ``train`` logs, relative to its largest recorded value)
    :param steps: the steps after the warm-up (or the updates)
    :return: 0 when there is nothing to compare
    """
    if quantity.startswith("updates/"):
        key = quantity.removeprefix("updates/")
        values, recorded = np.asarray(got["updates"][key]), np.asarray(expected["updates"][key])
        scale = np.abs(recorded).max()
    elif quantity == "actions":
        values, recorded, scale = np.asarray(got["actions"][WARMUP:]), np.asarray(expected["actions"][WARMUP:]), ACTION_BOUND
    else:
        values, recorded = np.asarray(got[quantity]), np.asarray(expected[quantity])
        scale = ACTION_BOUND if quantity == "candidates" else np.abs(recorded).max(axis=-1, keepdims=True)[steps]
    values, recorded = values[steps], recorded[steps]
    if values.size == 0:
        return 0.0
    return float((np.abs(values - recorded) / np.maximum(scale, 1e-12)).max())


def quantities(record: dict[str, Any]) -> list[str]:
    """The quantities of a run that :func:`deviation` compares."""
    selection = ["candidates", "e_q"] if record["chosen"] else []
    return ["actions", *selection, *(f"updates/{key}" for key in sorted(record["updates"]))]


def _dumps(golden: dict[str, dict[str, Any]]) -> str:
    """The cases and their quantities one per line, each value on its line (a long one for the lists)."""
    lines = []
    for name in sorted(golden):
        items = [f"  {json.dumps(key)}: {json.dumps(golden[name][key], sort_keys=True)}" for key in sorted(golden[name])]
        lines.append(f" {json.dumps(name)}: {{\n" + ",\n".join(items) + "\n }")
    return "{\n" + ",\n".join(lines) + "\n}"


def _drift(got: dict[str, Any], expected: dict[str, Any]) -> dict[str, Any]:
    """What ``tests/test_golden.py`` compares, as the largest deviation in the tight part and in the rest of the run."""
    from test_golden import TIGHT_STEPS, tolerance  # the test's tolerances (it imports this module: not at the top)

    end = horizon(expected, tolerance)
    first, rest = slice(0, min(TIGHT_STEPS, end)), slice(TIGHT_STEPS, end)
    drift: dict[str, Any] = {"horizon": end, "masks": got["masks"] == expected["masks"]}
    for quantity in quantities(expected):
        drift[quantity] = [float(f"{deviation(got, expected, quantity, steps):.2g}") for steps in (first, rest)]
    moved = [abs(got["moved"][part] - value) / value for part, value in expected["moved"].items() if value > 0]
    drift["moved"] = float(f"{max(moved):.2g}")
    return drift


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description="Record the golden runs, or measure how far a setting moves them.")
    parser.add_argument("cases", nargs="*", help="the cases (default: all)")
    parser.add_argument("--compare", action="store_true", help="compare with the recorded runs instead of recording")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the recording and the test use 1)")
    parser.add_argument("--save", type=Path, help="with --compare: also write the runs to this JSON file")
    args = parser.parse_args(argv)
    cases = args.cases or list(CASES)
    golden = json.loads(GOLDEN_FILE.read_text()) if GOLDEN_FILE.exists() else {}
    runs = {name: run_case(name, threads=args.threads) for name in cases}  # all first: then the file is written once
    if args.compare:
        for name, run in runs.items():
            print(name, json.dumps(_drift(run, golden[name])), flush=True)
        if args.save:
            args.save.write_text(json.dumps(runs) + "\n")
        return
    golden.update(runs)
    GOLDEN_FILE.write_text(_dumps(golden) + "\n")
    print(f"recorded {cases} in {GOLDEN_FILE}")


if __name__ == "__main__":
    main(sys.argv[1:])
