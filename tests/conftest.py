import os

import pytest
import torch as th

# One torch thread per test process: the suite runs with pytest-xdist on small machines.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
th.set_num_threads(1)


@pytest.fixture(autouse=True)
def _one_thread():
    th.set_num_threads(1)
    yield
