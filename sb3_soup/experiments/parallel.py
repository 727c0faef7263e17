"""
Execute a grid of runs: in local worker processes (one process per run, one torch thread each) or as tasks on a Ray
cluster.

Local workers are forked from a ``forkserver`` that has imported torch, SB3 and sb3_soup once (on platforms without
it, they are spawned), so a run's process starts in a fraction of a second rather than re-importing torch.

Each local run has a process of its own, so a run whose process dies (killed, out of memory, a crash in native code)
is reported as failed with its exit code while the others go on. Ctrl-C (locally) asks every running run to stop at
its next step and checkpoint; re-running the same command resumes them. Finished runs are skipped without starting a
worker, and runs that another ``run`` command is training (see :func:`~sb3_soup.experiments.runner.run_lock`) are
reported ``busy``.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from sb3_soup.experiments import runner
from sb3_soup.experiments.progress import ProgressBoard, progress_mode

_POLL_SECONDS = 0.5
_PRELOAD = ["torch", "stable_baselines3", "gymnasium", "sb3_soup", "sb3_soup.experiments.runner"]
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def available_cores() -> int:
    """
    :return: the cores this process may run on (its CPU affinity, which containers and ``taskset`` restrict),
        else the machine's core count
    """
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def _context() -> Any:
    """The multiprocessing context of local workers: a forkserver with the heavy modules preloaded, else spawn."""
    if "forkserver" not in mp.get_all_start_methods():  # pragma: no cover - Windows
        return mp.get_context("spawn")
    context = mp.get_context("forkserver")
    context.set_forkserver_preload(_PRELOAD)
    return context


def _limit_threads() -> None:
    """One BLAS/OpenMP/torch thread per worker: the grid's parallelism is across runs."""
    for name in _THREAD_VARIABLES:
        os.environ[name] = "1"


def _worker_main(spec_data: dict[str, Any], stop_event: Any, connection: Any) -> None:
    """A local worker process: thread limits, Ctrl-C turned into a clean resumable stop, one run, its result sent."""
    _limit_threads()
    runner.STOP_REQUESTED = stop_event

    def request_stop(signum: int, frame: Any) -> None:
        stop_event.set()

    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)
    connection.send(runner.run_one(spec_data))
    connection.close()


def _failed(spec: Any, message: str) -> dict[str, Any]:
    """Record and return the failure of a run whose worker died without reporting (so run_one could not)."""
    run_dir = Path(spec.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    runner.write_json(run_dir / runner.ERROR_FILE, {"error": message, "time": time.time()})
    status = runner.read_json(run_dir / runner.STATUS_FILE) or {}
    runner.report_status(run_dir, "failed", int(status.get("step", 0)), spec.timesteps, error=message)
    return {"key": spec.key, "run_dir": spec.run_dir, "status": "failed", "step": 0, "error": message}


def _exit_message(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        return f"worker process killed by {name}" + (" (out of memory?)" if name == "SIGKILL" else "")
    return (
        f"worker process exited with code {exitcode} without a result (its error is above; a script that calls "
        "run_local needs `if __name__ == '__main__':`)"
    )


def _skip_finished(specs: Sequence[Any]) -> tuple[dict[str, dict[str, Any]], list[Any]]:
    """The results of the runs that need no worker (finished already, or busy elsewhere), and the runs left to do."""
    results: dict[str, dict[str, Any]] = {}
    for spec in specs:
        result = {"key": spec.key, "run_dir": spec.run_dir}
        if runner.is_finished(spec):
            results[spec.key] = {**result, "status": "skipped", "step": spec.timesteps}
        elif (reason := runner.busy_reason(spec.run_dir)) is not None:
            results[spec.key] = {**result, "status": "busy", "step": 0, "error": reason}
    return results, [spec for spec in specs if spec.key not in results]


@dataclasses.dataclass
class _Worker:
    spec: Any
    process: Any
    connection: Any


def _raise_keyboard_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def run_local(specs: Sequence[Any], workers: int | None = None, progress: bool = True) -> list[dict[str, Any]]:
    """
    Run the grid in worker processes, one per run, at most ``workers`` at a time.

    :param specs: the runs
    :param workers: how many at once (default: the number of cores, see :func:`available_cores`)
    :param progress: show progress (bars in a terminal, lines otherwise)
    :return: one result per run (see :func:`~sb3_soup.experiments.runner.run_one`), in the order of ``specs``
    """
    results, todo = _skip_finished(specs)
    if not todo:
        return [results[spec.key] for spec in specs]
    workers = max(1, min(workers or available_cores(), len(todo)))
    context = _context()
    stop_event = context.Event()
    board = ProgressBoard(todo, progress_mode(progress))
    queue = list(todo)
    running: list[_Worker] = []
    interrupted = False
    # SIGTERM (`kill PID`, and what stops a command run in the background, where SIGINT is ignored) stops as Ctrl-C does
    in_main_thread = threading.current_thread() is threading.main_thread()  # where Python lets a handler be set
    previous = signal.signal(signal.SIGTERM, _raise_keyboard_interrupt) if in_main_thread else None
    try:
        while queue or running:
            try:
                while queue and len(running) < workers and not stop_event.is_set():
                    spec = queue.pop(0)
                    receive, send = context.Pipe(duplex=False)
                    process = context.Process(
                        target=_worker_main, args=(dataclasses.asdict(spec), stop_event, send), name=f"run {spec.key}"
                    )
                    process.start()
                    send.close()  # the child holds the only sending end: a dead child means end-of-file here
                    running.append(_Worker(spec, process, receive))
                if stop_event.is_set():  # interrupted: what never started stays to do
                    for spec in queue:
                        results[spec.key] = {"key": spec.key, "run_dir": spec.run_dir, "status": "interrupted", "step": 0}
                        board.finish(spec.key, results[spec.key])
                    queue.clear()
                # A worker's pipe turns readable when it sends its result, or at end-of-file when it dies.
                ready = mp.connection.wait([worker.connection for worker in running], timeout=_POLL_SECONDS)
            except KeyboardInterrupt:
                if interrupted:
                    raise
                interrupted = True
                stop_event.set()
                tqdm.write("Interrupted: checkpointing the running runs (Ctrl-C again to abort).", file=sys.stderr)
                continue
            for worker in [worker for worker in running if worker.connection in ready]:
                running.remove(worker)
                results[worker.spec.key] = _collect(worker)
                board.finish(worker.spec.key, results[worker.spec.key])
            board.poll()
    finally:
        if in_main_thread:
            signal.signal(signal.SIGTERM, previous)
        for worker in running:  # only after a second Ctrl-C or an error here: do not leave orphans behind
            worker.process.terminate()
            worker.process.join(10)
        board.close()
    return [results[spec.key] for spec in specs]


def _collect(worker: _Worker) -> dict[str, Any]:
    """The result a worker sent (it then exits), or a failure when it died without sending one."""
    try:
        result = worker.connection.recv()
    except (EOFError, OSError):
        result = None
    worker.connection.close()
    worker.process.join()
    if result is None:
        return _failed(worker.spec, _exit_message(worker.process.exitcode))
    return result


def run_ray(specs: Sequence[Any], address: str, workers: int | None = None, progress: bool = True) -> list[dict[str, Any]]:
    """
    Run the grid as Ray tasks (one CPU each) on a Ray cluster. ``address``: ``"auto"`` (the cluster this machine
    belongs to, after ``ray start``), ``"host:port"``, ``"ray://host:10001"`` (Ray Client, needs ``ray[client]``),
    or ``"local"`` to start a private single-machine instance. The ``sb3_soup`` package is shipped to the workers
    (``runtime_env.py_modules``); its dependencies (torch, SB3, gymnasium, MuJoCo) must be installed on every node.
    The runs write to their folders, made absolute here: on a multi-node cluster ``--out`` must be on a filesystem
    that every node mounts at the same path (the progress display and ``report`` read it too).

    A task that raises or whose worker dies is reported as failed and the others go on. Ctrl-C cancels the tasks;
    they resume from their last periodic checkpoint (``--checkpoint-freq``) on the next ``run``.

    :param specs: the runs
    :param address: the cluster's address
    :param workers: at most this many runs at once (default: as many as the cluster has CPUs for)
    :param progress: show progress (bars in a terminal, lines otherwise)
    :return: one result per run, in the order of ``specs``
    """
    try:
        import ray
    except ImportError as error:
        raise ImportError("The Ray backend needs ray: pip install 'sb3-soup[ray]'") from error
    import sb3_soup

    specs = [dataclasses.replace(spec, run_dir=str(Path(spec.run_dir).resolve())) for spec in specs]
    results, todo = _skip_finished(specs)
    if not todo:
        return [results[spec.key] for spec in specs]
    started_here = not ray.is_initialized()
    if started_here:
        runtime_env = {
            "py_modules": [str(Path(sb3_soup.__file__).resolve().parent)],
            "env_vars": {name: "1" for name in _THREAD_VARIABLES},
        }
        init_kwargs: dict[str, Any] = {"runtime_env": runtime_env, "log_to_driver": False}
        if address == "local":
            init_kwargs.update(num_cpus=workers or available_cores(), include_dashboard=False)
        ray.init(address=address, **init_kwargs)
    remote_run = ray.remote(num_cpus=1, max_retries=0)(runner.run_one)
    limit = workers or len(todo)
    queue = list(todo)
    pending: dict[Any, Any] = {}
    board = ProgressBoard(todo, progress_mode(progress))
    try:
        while queue or pending:
            while queue and len(pending) < limit:
                spec = queue.pop(0)
                pending[remote_run.remote(dataclasses.asdict(spec))] = spec
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=_POLL_SECONDS)
            for ref in ready:
                spec = pending.pop(ref)
                try:
                    results[spec.key] = ray.get(ref)
                except Exception as error:  # the task or its worker died
                    results[spec.key] = _failed(spec, f"{type(error).__name__}: {error}")
                board.finish(spec.key, results[spec.key])
            board.poll()
    except KeyboardInterrupt:
        for ref in pending:
            ray.cancel(ref)
        tqdm.write("Interrupted: the runs resume from their last periodic checkpoint.", file=sys.stderr)
        raise
    finally:
        board.close()
        if started_here:
            ray.shutdown()
    return [results[spec.key] for spec in specs]
