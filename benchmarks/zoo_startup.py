"""
Start-up cost of the RL Zoo import hook (``sb3_soup_zoo.pth`` -> ``_sb3_soup_zoo_hook``).

Times ``python -c pass`` with the hook enabled and disabled (``SB3_SOUP_ZOO_HOOK=0``, then the .pth only imports the
hook module, which returns at once), interleaved, and reports the medians and their difference; also the import time
of the hook module itself from ``python -X importtime``. The hook's bytecode is compiled first, as pip does when it
installs a wheel (an editable install under ``PYTHONDONTWRITEBYTECODE=1`` would otherwise recompile it at each start).

    python benchmarks/zoo_startup.py --runs 200
"""

import argparse
import os
import re
import statistics
import subprocess
import sys
import time


def time_start(enabled: bool) -> float:
    env = dict(os.environ, SB3_SOUP_ZOO_HOOK="1" if enabled else "0")
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", "pass"], env=env, check=True)
    return time.perf_counter() - start


def hook_import_us() -> int:
    """Cumulative import time (µs) of ``_sb3_soup_zoo_hook`` at start-up, from ``-X importtime``."""
    result = subprocess.run([sys.executable, "-X", "importtime", "-c", "pass"], capture_output=True, text=True, check=True)
    match = re.search(r"import time:\s+\d+ \|\s+(\d+) \|\s+_sb3_soup_zoo_hook\s*$", result.stderr, re.MULTILINE)
    if match is None:
        raise RuntimeError("_sb3_soup_zoo_hook is not imported at start-up: is sb3-soup installed in this Python?")
    return int(match.group(1))


def compile_hook() -> None:
    """Write the hook's ``.pyc`` (in a subprocess: this interpreter may have imported it already)."""
    code = "import importlib.util, py_compile; py_compile.compile(importlib.util.find_spec('_sb3_soup_zoo_hook').origin)"
    subprocess.run([sys.executable, "-c", code], check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=100, help="interpreter starts per setting")
    args = parser.parse_args()
    compile_hook()
    on, off = [], []
    for _ in range(args.runs):
        on.append(time_start(True))
        off.append(time_start(False))
    imports = sorted(hook_import_us() for _ in range(20))
    median_on, median_off = statistics.median(on) * 1e3, statistics.median(off) * 1e3
    print(f"python -c pass, {args.runs} runs each: hook enabled {median_on:.2f} ms, disabled {median_off:.2f} ms (medians)")
    print(f"difference of medians (installing the finder): {median_on - median_off:+.2f} ms")
    print(f"-X importtime of _sb3_soup_zoo_hook (20 starts): median {imports[len(imports) // 2]} us, min {imports[0]} us")


if __name__ == "__main__":
    main()
