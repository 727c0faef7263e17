"""The repository's scripts (``examples/``, ``benchmarks/``) as modules, for the tests that call their functions."""

import importlib.util
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[1]


def load_script(relative_path: str) -> ModuleType:
    """
    :param relative_path: the script's path in the repository, e.g. ``"benchmarks/throughput.py"``
    :return: the script as a module named after its file (its ``if __name__ == "__main__":`` block does not run)
    """
    path = REPO / relative_path
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
