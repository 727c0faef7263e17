"""
Execute a grid of runs: in local worker processes (spawned, one torch thread each) or as tasks on a Ray cluster.

Ctrl-C (locally) asks every running run to stop at its next step and checkpoint; re-running the same command
resumes them. A failing run is reported and does not stop the others.
"""

from __future__ import annotations

import concurrent.futures as futures
import dataclasses
import multiprocessing as mp
import os
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sb3_soup.experiments import runner
from sb3_soup.experiments.progress import ProgressBoard

_POLL_SECONDS = 0.5


def _limit_threads() -> None:
    """One BLAS/OpenMP/torch thread per worker: the grid's parallelism is across runs."""
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[name] = "1"


def _init_worker(stop_event: Any) -> None:
    """Initialise a local worker: thread limits, and Ctrl-C turned into a clean, resumable stop."""
    _limit_threads()
    runner.STOP_REQUESTED = stop_event

    def request_stop(signum: int, frame: Any) -> None:
        stop_event.set()

    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)


def _failed(spec: Any, error: BaseException) -> dict[str, Any]:
    message = f"{type(error).__name__}: {error}"
    runner.write_json(Path(spec.run_dir) / runner.ERROR_FILE, {"error": message, "time": time.time()})
    return {"key": spec.key, "run_dir": spec.run_dir, "status": "failed", "step": 0, "error": message}


def _log_result(results: dict[str, dict[str, Any]], total: int, key: str, enabled: bool) -> None:
    """Without progress bars (output not a terminal): one line per run that ends."""
    if enabled:
        result = results[key]
        print(f"[{len(results)}/{total}] {key}: {result['status']} at step {result['step']}", file=sys.stderr, flush=True)


def run_local(specs: Sequence[Any], workers: int | None = None, progress: bool = True) -> list[dict[str, Any]]:
    """
    Run the grid in a pool of spawned worker processes.

    :param specs: the runs
    :param workers: how many at once (default: the number of cores)
    :param progress: show progress bars
    :return: one result per run (see :func:`~sb3_soup.experiments.runner.run_one`), in the order of ``specs``
    """
    results: dict[str, dict[str, Any]] = {}
    for spec in specs:  # finished runs need no worker
        if runner.is_finished(spec):
            results[spec.key] = {"key": spec.key, "run_dir": spec.run_dir, "status": "skipped", "step": spec.timesteps}
    todo = [spec for spec in specs if spec.key not in results]
    if not todo:
        return [results[spec.key] for spec in specs]
    workers = max(1, min(workers or os.cpu_count() or 1, len(todo)))
    context = mp.get_context("spawn")
    stop_event = context.Event()
    board = ProgressBoard(todo, enabled=progress and sys.stderr.isatty())
    interrupted = False
    with futures.ProcessPoolExecutor(workers, mp_context=context, initializer=_init_worker, initargs=(stop_event,)) as pool:
        pending = {pool.submit(runner.run_one, dataclasses.asdict(spec)): spec for spec in todo}
        while pending:
            try:
                done, _ = futures.wait(pending, timeout=_POLL_SECONDS, return_when=futures.FIRST_COMPLETED)
            except KeyboardInterrupt:
                if interrupted:
                    raise
                interrupted = True
                stop_event.set()
                for future in pending:
                    future.cancel()
                print("\nInterrupted: checkpointing the running runs (Ctrl-C again to abort).", file=sys.stderr)
                continue
            for future in done:
                spec = pending.pop(future)
                if future.cancelled():
                    results[spec.key] = {"key": spec.key, "run_dir": spec.run_dir, "status": "interrupted", "step": 0}
                    continue
                try:
                    results[spec.key] = future.result()
                except Exception as error:  # the worker died (e.g. killed, out of memory)
                    results[spec.key] = _failed(spec, error)
                _log_result(results, len(specs), spec.key, progress and not board.enabled)
            board.poll()
    board.poll()
    board.close()
    return [results[spec.key] for spec in specs]


def run_ray(specs: Sequence[Any], address: str, progress: bool = True) -> list[dict[str, Any]]:
    """
    Run the grid as Ray tasks (one CPU each) on an existing cluster (``address``: ``"auto"``, ``"host:port"``,
    ``"ray://host:10001"``, or ``"local"`` to start a private one). The ``sb3_soup`` package is shipped to the
    workers (``runtime_env.py_modules``); the other dependencies must be installed there. The runs write to their
    ``run_dir``: on a multi-node cluster, ``--out`` must be on a filesystem shared by all nodes.

    :param specs: the runs
    :param address: the cluster's address
    :param progress: show progress bars
    :return: one result per run, in the order of ``specs``
    """
    try:
        import ray
    except ImportError as error:
        raise ImportError("The Ray backend needs ray: pip install 'sb3-soup[ray]'") from error
    import sb3_soup

    package_dir = str(Path(sb3_soup.__file__).resolve().parent)
    env_vars = {name: "1" for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=address, runtime_env={"py_modules": [package_dir], "env_vars": env_vars}, log_to_driver=False)
    remote_run = ray.remote(num_cpus=1, max_retries=0)(runner.run_one)
    pending = {remote_run.remote(dataclasses.asdict(spec)): spec for spec in specs}
    results: dict[str, dict[str, Any]] = {}
    board = ProgressBoard(specs, enabled=progress and sys.stderr.isatty())
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=_POLL_SECONDS)
            for ref in ready:
                spec = pending.pop(ref)
                try:
                    results[spec.key] = ray.get(ref)
                except Exception as error:  # the task or its worker died
                    results[spec.key] = _failed(spec, error)
                _log_result(results, len(specs), spec.key, progress and not board.enabled)
            board.poll()
    except KeyboardInterrupt:
        for ref in pending:
            ray.cancel(ref)
        print("\nInterrupted: the runs resume from their last periodic checkpoint.", file=sys.stderr)
        raise
    finally:
        board.close()
        if started_here:
            ray.shutdown()
    return [results[spec.key] for spec in specs]
