"""
Execute a grid of runs with :func:`run_grid`: one loop (skip what is done, start runs up to the capacity, collect
their results, show progress, stop on Ctrl-C or SIGTERM) over one :class:`Scheduler` interface, with two schedulers
behind it: local worker processes (the default) or tasks on a Ray cluster (``ray_address``).

Local workers are forked from a ``forkserver`` that has imported torch, SB3 and sb3_soup once (on platforms without
it, they are spawned), so a run's process starts in a fraction of a second rather than re-importing torch (a local
Ray instance takes several seconds to start, and its workers import torch themselves).

Each local run has a process of its own, so a run whose process dies (killed, out of memory, a crash in native code)
is reported as failed with its exit code while the others go on. Ctrl-C or SIGTERM (locally) asks every running run
to stop at the end of its rollout and checkpoint; re-running the same command resumes them. Finished runs are skipped
without starting a worker, and runs that another ``run`` command is training (see
:func:`~sb3_soup.experiments.runner.run_lock`) are reported ``busy``.
"""

from __future__ import annotations

import abc
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


def _failed(spec: Any, message: str) -> dict[str, Any]:
    """Record and return the failure of a run whose worker died without reporting (so run_one could not)."""
    run_dir = Path(spec.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    runner.write_json(run_dir / runner.ERROR_FILE, {"error": message, "time": time.time()})
    status = runner.read_json(run_dir / runner.STATUS_FILE) or {}
    runner.report_status(run_dir, "failed", int(status.get("step", 0)), spec.timesteps, error=message)
    return {"key": spec.key, "run_dir": spec.run_dir, "status": "failed", "step": 0, "error": message}


class Scheduler(abc.ABC):
    """
    Where the runs of a grid execute. :func:`run_grid` submits runs while fewer than :attr:`capacity` are running and
    collects the results of those that ended.

    :param capacity: how many runs may execute at once
    """

    stop_message = ""
    """What Ctrl-C does to the running runs, shown when it is pressed."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity

    @property
    @abc.abstractmethod
    def running(self) -> int:
        """How many runs are executing."""

    @abc.abstractmethod
    def submit(self, spec: Any) -> None:
        """
        Start a run.

        :param spec: its :class:`~sb3_soup.experiments.grid.RunSpec`
        """

    @abc.abstractmethod
    def wait(self, timeout: float) -> list[tuple[Any, dict[str, Any]]]:
        """
        :param timeout: seconds to wait at most for a run to end
        :return: the runs that ended, each with its result (see :func:`~sb3_soup.experiments.runner.run_one`)
        """

    @abc.abstractmethod
    def stop(self) -> bool:
        """
        Stop the running runs (Ctrl-C or SIGTERM).

        :return: True when they stop cleanly and their results are still to be collected, False when they were
            cancelled (the caller gives up on them)
        """

    @abc.abstractmethod
    def close(self) -> None:
        """Release what the scheduler holds (after a second Ctrl-C or an error: end the runs still executing)."""


def _context() -> Any:
    """The multiprocessing context of local workers: a forkserver with the heavy modules preloaded, else spawn."""
    if "forkserver" not in mp.get_all_start_methods():  # pragma: no cover - Windows
        return mp.get_context("spawn")
    context = mp.get_context("forkserver")
    context.set_forkserver_preload(_PRELOAD)
    return context


def _worker_main(spec_data: dict[str, Any], stop_event: Any, connection: Any) -> None:
    """A local worker process: thread limits, Ctrl-C turned into a clean resumable stop, one run, its result sent."""
    for name in _THREAD_VARIABLES:  # one thread per worker: the grid's parallelism is across runs
        os.environ[name] = "1"
    runner.STOP_REQUESTED = stop_event

    def request_stop(signum: int, frame: Any) -> None:
        stop_event.set()

    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)
    connection.send(runner.run_one(spec_data))
    connection.close()


def _exit_message(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        return f"worker process killed by {name}" + (" (out of memory?)" if name == "SIGKILL" else "")
    return (
        f"worker process exited with code {exitcode} without a result (its error is above; a script that calls "
        "run_grid needs `if __name__ == '__main__':`)"
    )


@dataclasses.dataclass
class _Worker:
    spec: Any
    process: Any
    connection: Any


class LocalProcesses(Scheduler):
    """
    One worker process per run, forked from a forkserver (see the module's docstring). Stopping asks every running run
    to stop at the end of its rollout and checkpoint.

    :param capacity: how many runs at once
    """

    stop_message = "Interrupted: checkpointing the running runs (Ctrl-C again to abort)."

    def __init__(self, capacity: int) -> None:
        super().__init__(capacity)
        self.context = _context()
        self.stop_event = self.context.Event()
        self.workers: list[_Worker] = []

    @property
    def running(self) -> int:
        return len(self.workers)

    def submit(self, spec: Any) -> None:
        receive, send = self.context.Pipe(duplex=False)
        process = self.context.Process(
            target=_worker_main, args=(dataclasses.asdict(spec), self.stop_event, send), name=f"run {spec.key}"
        )
        process.start()
        send.close()  # the child holds the only sending end: a dead child means end-of-file here
        self.workers.append(_Worker(spec, process, receive))

    def wait(self, timeout: float) -> list[tuple[Any, dict[str, Any]]]:
        # A worker's pipe turns readable when it sends its result, or at end-of-file when it dies.
        ready = mp.connection.wait([worker.connection for worker in self.workers], timeout=timeout)
        ended = [worker for worker in self.workers if worker.connection in ready]
        for worker in ended:
            self.workers.remove(worker)
        return [(worker.spec, self._collect(worker)) for worker in ended]

    @staticmethod
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

    def stop(self) -> bool:
        self.stop_event.set()
        return True

    def close(self) -> None:
        for worker in self.workers:  # only after a second Ctrl-C or an error: do not leave orphans behind
            worker.process.terminate()
            worker.process.join(10)


class RayTasks(Scheduler):
    """
    One Ray task (one CPU) per run. ``address``: ``"auto"`` (the cluster this machine belongs to, after
    ``ray start``), ``"host:port"``, ``"ray://host:10001"`` (Ray Client, needs ``ray[client]``), or ``"local"`` to
    start a private single-machine instance. The ``sb3_soup`` package is shipped to the workers
    (``runtime_env.py_modules``); its dependencies (torch, SB3, gymnasium, MuJoCo) must be installed on every node.
    A task that raises or whose worker dies is reported as failed. Stopping cancels the tasks: they resume from their
    last periodic checkpoint (``--checkpoint-freq``).

    :param capacity: how many runs at once
    :param address: the cluster's address
    :param cpus: the CPUs of a ``"local"`` instance
    """

    stop_message = "Interrupted: the runs resume from their last periodic checkpoint."

    def __init__(self, capacity: int, address: str, cpus: int) -> None:
        try:
            import ray
        except ImportError as error:
            raise ImportError("The Ray backend needs ray: pip install 'sb3-soup[ray]'") from error
        import sb3_soup

        super().__init__(capacity)
        self.ray = ray
        self.started_here = not ray.is_initialized()
        if self.started_here:
            runtime_env = {
                "py_modules": [str(Path(sb3_soup.__file__).resolve().parent)],
                "env_vars": {name: "1" for name in _THREAD_VARIABLES},
            }
            init_kwargs: dict[str, Any] = {"runtime_env": runtime_env, "log_to_driver": False}
            if address == "local":
                init_kwargs.update(num_cpus=cpus, include_dashboard=False)
            ray.init(address=address, **init_kwargs)
        self.remote_run = ray.remote(num_cpus=1, max_retries=0)(runner.run_one)
        self.pending: dict[Any, Any] = {}

    @property
    def running(self) -> int:
        return len(self.pending)

    def submit(self, spec: Any) -> None:
        self.pending[self.remote_run.remote(dataclasses.asdict(spec))] = spec

    def wait(self, timeout: float) -> list[tuple[Any, dict[str, Any]]]:
        ready, _ = self.ray.wait(list(self.pending), num_returns=1, timeout=timeout)
        ended = []
        for ref in ready:
            spec = self.pending.pop(ref)
            try:
                result = self.ray.get(ref)
            except Exception as error:  # the task or its worker died
                result = _failed(spec, f"{type(error).__name__}: {error}")
            ended.append((spec, result))
        return ended

    def stop(self) -> bool:
        for ref in self.pending:
            self.ray.cancel(ref)
        return False

    def close(self) -> None:
        if self.started_here:
            self.ray.shutdown()


class _StopSignals:
    """
    Count Ctrl-C (SIGINT) and SIGTERM (``kill PID``, and what stops a command run in the background, where SIGINT is
    ignored) while a grid runs, for :func:`run_grid`'s loop to act on between two of its steps. The handlers only count:
    an exception raised wherever the main thread happens to be could land inside a worker's start, after its process
    was forked but before the scheduler recorded it (a window of seconds on a first start, while the forkserver imports
    torch), and leave that worker training on, unsupervised, once the runner had stopped. SIGINT is counted only where
    Python's default handler is in place (not where it is ignored, as in a background job, nor where a caller installed
    another). Signal handlers belong to the main thread: from another thread (a caller's), none is installed.
    """

    def __init__(self) -> None:
        self.received = 0
        self._previous: dict[int, Any] = {}

    def _count(self, signum: int, frame: Any) -> None:
        self.received += 1

    def __enter__(self) -> _StopSignals:
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                if signum == signal.SIGINT and signal.getsignal(signum) is not signal.default_int_handler:
                    continue
                self._previous[signum] = signal.signal(signum, self._count)
        return self

    def __exit__(self, *exc_info: Any) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous.clear()


def _skip_finished(specs: Sequence[Any]) -> tuple[dict[str, dict[str, Any]], list[Any]]:
    """The results of the runs that need no worker (finished already, or busy elsewhere), and the runs left to do."""
    results: dict[str, dict[str, Any]] = {}
    for spec in specs:
        result = {"key": spec.key, "run_dir": spec.run_dir}
        if runner.is_finished(spec):
            results[spec.run_id] = {**result, "status": "skipped", "step": spec.timesteps}
        elif (reason := runner.busy_reason(spec.run_dir)) is not None:
            results[spec.run_id] = {**result, "status": "busy", "step": 0, "error": reason}
    return results, [spec for spec in specs if spec.run_id not in results]


def run_grid(
    specs: Sequence[Any], workers: int | None = None, progress: bool = True, ray_address: str | None = None
) -> list[dict[str, Any]]:
    """
    Run a grid: each run in a local worker process, or as a Ray task when ``ray_address`` is given (see
    :class:`RayTasks`; the runs' folders are made absolute: on a multi-node cluster they must be on a filesystem that
    every node mounts at the same path, which the progress display and ``report`` read too).

    :param specs: the runs
    :param workers: at most this many at once (default: locally, the number of cores, see :func:`available_cores`;
        on Ray, as many as the cluster has CPUs for)
    :param progress: show progress (bars in a terminal, lines otherwise)
    :param ray_address: the Ray cluster's address, or None to run locally
    :return: one result per run (see :func:`~sb3_soup.experiments.runner.run_one`), in the order of ``specs``
    """
    if ray_address is not None:
        specs = [dataclasses.replace(spec, run_dir=str(Path(spec.run_dir).resolve())) for spec in specs]
    results, todo = _skip_finished(specs)
    if not todo:
        return [results[spec.run_id] for spec in specs]
    scheduler: Scheduler
    if ray_address is not None:
        scheduler = RayTasks(workers or len(todo), ray_address, cpus=workers or available_cores())
    else:
        scheduler = LocalProcesses(max(1, min(workers or available_cores(), len(todo))))
    board = ProgressBoard(todo, progress_mode(progress))
    queue = list(todo)
    stopping = False
    try:
        with _StopSignals() as signals:
            while queue or scheduler.running:
                try:
                    while queue and not signals.received and scheduler.running < scheduler.capacity:
                        scheduler.submit(queue[0])
                        queue.pop(0)  # once submitted: a run whose submission was interrupted stays to do
                    ended = scheduler.wait(_POLL_SECONDS)
                except KeyboardInterrupt:  # from a SIGINT handler left in place (see _StopSignals)
                    signals.received += 1
                    ended = []
                for spec, result in ended:
                    results[spec.run_id] = result
                    board.finish(board.name(spec), result)
                if signals.received and not stopping:
                    stopping = True
                    tqdm.write(scheduler.stop_message, file=sys.stderr)
                    for spec in queue:  # what never started stays to do
                        results[spec.run_id] = {"key": spec.key, "run_dir": spec.run_dir, "status": "interrupted", "step": 0}
                        board.finish(board.name(spec), results[spec.run_id])
                    queue.clear()
                    if not scheduler.stop():
                        raise KeyboardInterrupt
                if signals.received > 1:  # a second signal aborts: close() ends the runs still executing
                    raise KeyboardInterrupt
                board.poll()
    finally:
        scheduler.close()
        board.close()
    return [results[spec.run_id] for spec in specs]
