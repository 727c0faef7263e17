"""The golden runs recorded before the redesign (tests/golden.py) are reproduced: same actions, same parameters."""

import json

import numpy as np
import pytest
from golden import CASES, GOLDEN_FILE, run_case

GOLDEN = json.loads(GOLDEN_FILE.read_text())


def test_every_case_is_recorded():
    assert sorted(GOLDEN) == sorted(CASES)


@pytest.mark.parametrize("name", sorted(CASES))
def test_golden_run_is_reproduced(name):
    expected, got = GOLDEN[name], run_case(name)
    np.testing.assert_allclose(got["actions"], expected["actions"], rtol=0, atol=1e-6)
    # the sha256 pins the exact bits on the machine that recorded them; another CPU may round differently
    assert got["parameter_sum"] == pytest.approx(expected["parameter_sum"], rel=1e-7)
    assert got["parameter_abs_sum"] == pytest.approx(expected["parameter_abs_sum"], rel=1e-7)
