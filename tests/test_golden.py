"""
The golden runs recorded before the redesign of the core (tests/golden.py) are reproduced, on any x86-64 CPU and
with any torch and SB3 the install admits.

The recording machine's bits are not: another CPU (its kernels), another BLAS code path or another torch rounds the
first forward pass differently, by about 1e-7, and training amplifies that (issue 21). The amplification comes in
bursts, not gradually: Adam's normalised step turns the rounding noise of a near-zero gradient into a full step of
the learning rate, and a near-tie between two candidates' E-Q values can make two machines execute different actions
from there on. So the test compares, at tolerances measured across such settings (``python tests/golden.py
--compare``, see its docstring; on issue 21, against the recording's AVX2 kernels: ``ATEN_CPU_CAPABILITY=default``,
torch's kernels for any x86-64 CPU, and ``MKL_CBWR=COMPATIBLE``, MKL's; two threads and
``MKL_ENABLE_INSTRUCTIONS=SSE4_2`` changed no bit, nor did the oldest SB3 and gymnasium the install admits, 2.3.2
and 0.29.1):

- exactly, over the whole run, what no rounding reaches: the random warm-up's actions, the bootstrap masks (NumPy
  draws, as many per step whatever the values), the schedules ``train`` logs (to 1e-12), and which heads training
  moved at all (the heads of the pairs that were never trained keep their values bit for bit);
- closely (:data:`TIGHT`) the first :data:`TIGHT_STEPS` steps after the warm-up and their updates: the executed
  actions, every head's candidate action and E-Q value, the head chosen, every value ``train`` logs (the losses of
  eqs. 3, 5 and 8). A refactoring that changes the algorithm (a head's target, a mask, the critic that scores an
  actor head, the selection) changes them from the first update on, by far more than rounding does;
- loosely (:data:`LOOSE`) the rest of the run, up to the recorded run's horizon (:func:`golden.horizon`): the first
  step whose choice a difference within the tolerance could flip. The runs with one actor head have none and are
  compared whole, with how far training moved each network's body and each of its heads; those with several meet one
  (dbddpg and soup after 9 to 11 steps, multi_ddpg after 20, fixed and decayed after 28 and 70): their near-tied
  candidates are why 300 steps cannot be compared whole on another machine.
"""

import json

import numpy as np
import pytest
from golden import CASES, GOLDEN_FILE, STEPS, WARMUP, deviation, horizon, quantities, run_case

GOLDEN = json.loads(GOLDEN_FILE.read_text())

# Measured drifts (issue 21), relative to each quantity's scale, in the first 20 steps after the warm-up: at most
# 4.6e-6 (the E-Q values, relative to each step's largest: at the first step they are near 0.01), 3.9e-7 for the
# losses, 2.4e-7 for the actions. TIGHT leaves a margin of 10 above that, and lies far below what a change of the
# algorithm does at its first updates (see issue 21's fault injections: 1e-3 and more).
TIGHT = 5e-5
TIGHT_STEPS = 20
# Over the rest of the run at most 8.1e-4 (ma_bddpg-active's actor loss with ATEN_CPU_CAPABILITY=default: bursts of
# Adam steps of the learning rate's size), 7.1e-4 for how far a body or head moved, 5.1e-5 for the actions: a margin
# of 12 or more. The changes of the algorithm tried on issue 21 moved the networks by 2e-2 to 1.1 more or less.
LOOSE = 1e-2
# Every case is compared over at least this many steps and updates (the K x K cases' horizons are 9 to 11)
MIN_STEPS = 8
# Logged but not compared: the spread of nearly equal logits (their std at the first updates) is all cancellation
NOT_COMPARED = ("updates/selection_logit_spread",)
SCHEDULES = ("n_updates", "learning_rate", "critic_learning_rate", "noise_std")  # Python arithmetic, no tensor


def tolerance(t: int) -> float:
    """The relative tolerance at step ``t`` after the warm-up (and at the update that follows it)."""
    return TIGHT if t < TIGHT_STEPS else LOOSE


def clear_choices(record: dict, steps: range) -> list[int]:
    """The steps whose chosen candidate leads every other by more than twice the tolerance: another machine's too."""
    clear = []
    for t in steps:
        e_q = np.asarray(record["e_q"][t])
        lead = np.delete(e_q[record["chosen"][t]] - e_q, record["chosen"][t])
        if (lead > 2 * tolerance(t) * np.abs(e_q).max()).all():
            clear.append(t)
    return clear


def test_every_case_is_recorded():
    assert sorted(GOLDEN) == sorted(CASES)


@pytest.mark.parametrize("name", sorted(CASES))
def test_the_first_steps_are_always_compared(name):
    """No recorded choice in the first steps is within reach of rounding: every case is compared there."""
    assert horizon(GOLDEN[name], tolerance) >= MIN_STEPS


def test_some_cases_are_compared_to_the_end():
    whole = [name for name in CASES if horizon(GOLDEN[name], tolerance) == STEPS - WARMUP]
    assert {"ddpg-active", "ddpg-all", "ma_bddpg-active", "ma_bddpg-all"} <= set(whole)


@pytest.mark.parametrize("name", sorted(CASES))
def test_golden_run_is_reproduced(name):
    expected, got = GOLDEN[name], run_case(name)
    end = horizon(expected, tolerance)

    # exactly: what no rounding reaches
    assert got["actions"][:WARMUP] == expected["actions"][:WARMUP], "the random warm-up"
    assert got["masks"] == expected["masks"], "the bootstrap masks"
    for key in SCHEDULES:  # Python floats: exact but for the last bit of a libm's pow (the noise's decay)
        assert got["updates"][key] == pytest.approx(expected["updates"][key], rel=1e-12, abs=0), key
    assert {part: value > 0 for part, value in got["moved"].items()} == {
        part: value > 0 for part, value in expected["moved"].items()
    }, "which networks and heads training moved"

    # closely: the first steps and their updates
    first, rest = slice(0, min(TIGHT_STEPS, end)), slice(TIGHT_STEPS, end)
    compared = [quantity for quantity in quantities(expected) if quantity not in NOT_COMPARED]
    for quantity in compared:
        assert deviation(got, expected, quantity, first) <= TIGHT, f"{quantity} in steps 0-{first.stop}"
    # loosely: the rest of the run, as far as the recorded run's choices are clear
    for quantity in compared:
        assert deviation(got, expected, quantity, rest) <= LOOSE, f"{quantity} in steps {TIGHT_STEPS}-{end}"
    if expected["chosen"]:
        clear = clear_choices(expected, range(end))
        assert [got["chosen"][t] for t in clear] == [expected["chosen"][t] for t in clear], "the heads chosen"
    if end == STEPS - WARMUP:
        for part, value in expected["moved"].items():
            assert got["moved"][part] == pytest.approx(value, rel=LOOSE), f"how far training moved {part}"
