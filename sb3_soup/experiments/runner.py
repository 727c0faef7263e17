"""
Train one (model, seed) run in the current process: build or resume the model, log, checkpoint, mark it done.

The run's folder holds ``spec.json`` (its :class:`~sb3_soup.experiments.grid.RunSpec`), ``monitor.csv``,
``progress.csv``, ``evaluations.csv`` (deterministic evaluations every ``eval_freq`` steps, as SB3's ``EvalCallback``),
``status.json`` (step reached, for the progress bars, and the time spent training), ``checkpoints/`` while it runs
(:mod:`sb3_soup.checkpoint`'s, the newest only: a stopped or killed run resumes exactly from it), and at the end
``model.zip`` plus ``done.json``, or ``error.json`` when it failed. While a process trains the run it holds an
exclusive lock on ``run.lock``, so that two ``run`` commands given the same folder (e.g. two suites sharing runs)
never train one run twice at once: the second reports it ``busy``. Heavy imports (torch, SB3) happen inside
:func:`run_one` so that worker processes can limit torch's threads first.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import socket
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from stable_baselines3.common.base_class import BaseAlgorithm

try:
    import fcntl
except ImportError:  # pragma: no cover - not on Windows: runs are then not locked
    fcntl = None  # type: ignore[assignment]

SPEC_FILE = "spec.json"
STATUS_FILE = "status.json"
DONE_FILE = "done.json"
ERROR_FILE = "error.json"
FINAL_MODEL = "model.zip"
LOCK_FILE = "run.lock"
CHECKPOINT_DIR = "checkpoints"
LOCKING = fcntl is not None
"""Whether runs are locked on this platform (``flock``; not on Windows)."""

# Set by a signal handler or by the parent (see parallel.py): finish the current step, checkpoint, stop.
STOP_REQUESTED = threading.Event()


def write_json(path: str | os.PathLike, data: dict[str, Any]) -> None:
    """
    Write JSON atomically (:func:`sb3_soup.checkpoint.atomic_write`), so readers never see half a file.

    :param path: the file
    :param data: the data
    """
    from sb3_soup.checkpoint import atomic_write  # it brings torch and SB3: imported when needed (see the module doc)

    text = json.dumps(data, indent=2, sort_keys=True, default=str)
    atomic_write(path, lambda tmp: tmp.write_text(text))


def read_json(path: str | os.PathLike) -> dict[str, Any] | None:
    """
    :param path: the file
    :return: its data, or ``None`` when it is missing or unreadable
    """
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def resolve_policy_kwargs(value: Any) -> dict[str, Any] | None:
    """
    :param value: ``policy_kwargs`` as a dict, ``None``, or an RL-Zoo style expression string
        such as ``"dict(net_arch=[64, 64], activation_fn=nn.ReLU)"``
    :return: the dict
    """
    if value is None or isinstance(value, dict):
        return value
    import torch as th

    # Same convention as the RL Zoo, which evaluates these strings: names from torch only.
    return eval(value, {"__builtins__": {}, "dict": dict, "nn": th.nn, "th": th, "torch": th})


def algo_class(algo: str) -> type[BaseAlgorithm]:
    """
    :param algo: ``"soup"``, ``"td3"``, ``"sb3_ddpg"`` or ``"sac"``
    :return: the class that trains it
    """
    if algo == "soup":
        try:
            from sb3_soup import SOUP  # type: ignore[attr-defined]
        except ImportError as error:
            raise ImportError("sb3_soup.SOUP is not available (the core algorithm is not installed on this branch)") from error
        return SOUP
    from stable_baselines3 import DDPG, SAC, TD3

    classes: dict[str, type] = {"td3": TD3, "sb3_ddpg": DDPG, "sac": SAC}
    if algo not in classes:
        raise ValueError(f"Unknown algorithm {algo!r}")
    return classes[algo]


def build_model(spec: Any, env: Any) -> Any:
    """
    A fresh model for a run.

    :param spec: the run's :class:`~sb3_soup.experiments.grid.RunSpec`
    :param env: its (vectorised, monitored) environment
    :return: the model
    """
    import gymnasium as gym
    import numpy as np

    from sb3_soup.noise import zoo_action_noise

    kwargs = dict(spec.hyperparams)
    kwargs["policy_kwargs"] = resolve_policy_kwargs(kwargs.get("policy_kwargs"))
    if kwargs["policy_kwargs"] is None:
        del kwargs["policy_kwargs"]
    policy = "MultiInputPolicy" if isinstance(env.observation_space, gym.spaces.Dict) else "MlpPolicy"
    # the exploration noise, as the RL Zoo's keys: noise_type "decaying_normal" (the paper's SOUP noise), else a constant
    # NormalActionNoise of std noise_std (the SB3 peers')
    kwargs = zoo_action_noise(kwargs, env.action_space.shape)
    if "noise_std" in kwargs:
        from stable_baselines3.common.noise import NormalActionNoise

        n_actions = int(np.prod(env.action_space.shape))
        noise_std = float(kwargs.pop("noise_std"))
        kwargs["action_noise"] = NormalActionNoise(np.zeros(n_actions), noise_std * np.ones(n_actions))
    return algo_class(spec.algo)(policy, env, seed=spec.seed, device="cpu", verbose=0, **kwargs)


def evaluation_seed(run_seed: int, step: int) -> int:
    """
    The seed of the evaluation episodes at ``step``: a function of the run's seed and the step only, so that a resumed
    run evaluates on the same episodes as an uninterrupted one, and every model of a seed on the same ones.

    :param run_seed: the run's seed
    :param step: the training step
    :return: the seed
    """
    import numpy as np

    return int(np.random.SeedSequence([run_seed, step]).generate_state(1)[0])


def evaluate(model: Any, env: Any, step: int, spec: Any, run_dir: Path) -> None:
    """
    Evaluate the deterministic policy for ``spec.eval_episodes`` episodes (SB3's ``evaluate_policy``, as
    ``EvalCallback`` does) and append them to ``evaluations.csv``. Acting greedily draws nothing from the training's
    random generators, so evaluating does not change the run.

    :param model: the model
    :param env: the evaluation env (a VecEnv of one Monitor-wrapped env)
    :param step: the training step
    :param spec: the run's :class:`~sb3_soup.experiments.grid.RunSpec`
    :param run_dir: the run's folder
    """
    from stable_baselines3.common.evaluation import evaluate_policy

    from sb3_soup.experiments import logs

    env.seed(evaluation_seed(spec.seed, step))
    returns, lengths = evaluate_policy(
        model, env, n_eval_episodes=spec.eval_episodes, deterministic=True, return_episode_rewards=True, warn=False
    )
    logs.append_evaluation(run_dir, step, list(returns), list(lengths))  # type: ignore[arg-type]


def _make_callback(spec: Any, run_dir: Path, start_step: int, wall_time: Callable[[], float], eval_env: Any) -> Any:
    """The callback doing progress reports, evaluations and resumable stops."""
    from stable_baselines3.common.callbacks import BaseCallback

    from sb3_soup.checkpoint import StopTraining

    class RunCallback(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.last_report = 0.0
            self.stopped = False

        def _on_step(self) -> bool:
            if spec.eval_freq > 0 and self.num_timesteps % spec.eval_freq == 0:
                evaluate(self.model, eval_env, self.num_timesteps, spec, run_dir)
            now = time.monotonic()
            if now - self.last_report > 1.0:
                self.last_report = now
                report_status(run_dir, "running", self.num_timesteps, spec.timesteps, wall_time_s=wall_time())
            new_steps = self.num_timesteps - start_step
            if STOP_REQUESTED.is_set() or (spec.stop_after is not None and new_steps >= spec.stop_after):
                self.stopped = True  # leave at the end of this rollout, where a checkpoint resumes exactly
            return True

        def _on_rollout_start(self) -> None:
            # Between two rollouts: the model, its buffer and the env agree (see sb3_soup.checkpoint)
            if self.stopped:
                raise StopTraining

    return RunCallback()


def report_status(run_dir: str | os.PathLike, status: str, step: int, total: int, **extra: Any) -> None:
    """
    Record how far a run is (read by the progress bars and by ``report``).

    :param run_dir: the run's folder
    :param status: ``"running"``, ``"finished"``, ``"interrupted"`` or ``"failed"``
    :param step: steps done
    :param total: steps in all
    :param extra: more fields, e.g. ``wall_time_s``, the seconds spent training the run so far (when it is not given,
        as for a failure, the previous status' value is kept)
    """
    path = Path(run_dir) / STATUS_FILE
    data = {"status": status, "step": int(step), "total": int(total), "time": time.time()}
    if "wall_time_s" not in extra:
        data["wall_time_s"] = (read_json(path) or {}).get("wall_time_s", 0.0)
    data.update(pid=os.getpid(), host=socket.gethostname(), **extra)
    write_json(path, data)


class RunBusy(RuntimeError):
    """Another process is training this run."""


def busy_reason(run_dir: str | os.PathLike) -> str | None:
    """
    Whether another process trains the run now, checked without taking the lock or creating any file (the parent
    process uses it to avoid starting a worker for nothing; the worker's :func:`run_lock` decides).

    :param run_dir: the run's folder
    :return: why it is busy, ``None`` when it is not
    """
    path = Path(run_dir) / LOCK_FILE
    if fcntl is None or not path.exists():
        return None
    with open(path) as stream:
        try:
            fcntl.flock(stream, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return f"{run_dir} is being trained by {stream.read().strip() or 'another process'}"
        fcntl.flock(stream, fcntl.LOCK_UN)
    return None


@contextlib.contextmanager
def run_lock(run_dir: str | os.PathLike) -> Iterator[None]:
    """
    Hold the run's lock while training it. The lock is an ``flock`` on ``run.lock``: the system drops it when the
    process ends, however it ends, so a crashed run never stays locked.

    :param run_dir: the run's folder
    :raises RunBusy: when another process holds it
    """
    run_dir = Path(run_dir)
    path = run_dir / LOCK_FILE
    if fcntl is None:
        yield
        return
    with open(path, "a+") as stream:
        try:
            fcntl.flock(stream, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            stream.seek(0)
            owner = stream.read().strip() or "another process"
            raise RunBusy(f"{run_dir} is being trained by {owner}") from error
        stream.seek(0)
        stream.truncate()
        stream.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        stream.flush()
        try:
            yield
        finally:
            fcntl.flock(stream, fcntl.LOCK_UN)


def _check_spec(spec: Any, run_dir: Path) -> None:
    """Refuse to continue a run folder created with other settings."""
    previous = read_json(run_dir / SPEC_FILE)
    if previous is None:
        return
    from sb3_soup.experiments.grid import RunSpec

    old = RunSpec(**previous).config()
    new = spec.config()
    if old != new:
        changed = sorted(key for key in set(old) | set(new) if old.get(key) != new.get(key))
        raise ValueError(
            f"{run_dir} holds a run with other settings (differs in: {', '.join(changed)}); "
            "use another --out folder or delete that run"
        )


def is_finished(spec: Any) -> bool:
    """
    :param spec: a run's :class:`~sb3_soup.experiments.grid.RunSpec`
    :return: whether its folder holds this run, finished
    """
    run_dir = Path(spec.run_dir)
    if not (run_dir / DONE_FILE).is_file():
        return False
    try:
        _check_spec(spec, run_dir)
    except ValueError:
        return False
    return True


def run_one(spec_data: dict[str, Any]) -> dict[str, Any]:
    """
    Train (or resume, or skip if finished) one run. Never raises for a failing run: the error is written to
    ``error.json`` and returned.

    :param spec_data: the run's :class:`~sb3_soup.experiments.grid.RunSpec` as a dict
    :return: ``{"key", "run_dir", "status", "step", "error"?}`` with status ``"finished"``, ``"skipped"`` (it was
        finished already), ``"interrupted"`` (stopped early; resumable), ``"busy"`` (another process is training it)
        or ``"failed"``
    """
    from sb3_soup.experiments.grid import RunSpec

    spec = RunSpec(**spec_data)
    run_dir = Path(spec.run_dir)
    result: dict[str, Any] = {"key": spec.key, "run_dir": str(run_dir)}
    step = 0
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        with run_lock(run_dir):
            _check_spec(spec, run_dir)
            if (run_dir / DONE_FILE).is_file():
                done = read_json(run_dir / DONE_FILE) or {}
                return {**result, "status": "skipped", "step": done.get("timesteps", spec.timesteps)}
            if STOP_REQUESTED.is_set():
                return {**result, "status": "interrupted", "step": 0}
            write_json(run_dir / SPEC_FILE, dataclasses.asdict(spec))
            (run_dir / ERROR_FILE).unlink(missing_ok=True)
            status, step = _train(spec, run_dir)
            return {**result, "status": status, "step": step}
    except RunBusy as error:
        return {**result, "status": "busy", "step": 0, "error": str(error)}
    except Exception as error:
        message = f"{type(error).__name__}: {error}"
        write_json(run_dir / ERROR_FILE, {"error": message, "traceback": traceback.format_exc(), "time": time.time()})
        report_status(run_dir, "failed", step, spec.timesteps, error=message)
        return {**result, "status": "failed", "step": step, "error": message}


def _train(spec: Any, run_dir: Path) -> tuple[str, int]:
    """Build or resume the model and train it; return (status, steps done)."""
    import gymnasium as gym
    import torch as th
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    from sb3_soup.checkpoint import (
        ResumableCheckpointCallback,
        StopTraining,
        latest_checkpoint,
        load_checkpoint,
        save_checkpoint,
    )
    from sb3_soup.experiments import logs

    th.set_num_threads(1)
    checkpoints = run_dir / CHECKPOINT_DIR
    checkpoint = latest_checkpoint(checkpoints)
    earlier = (read_json(run_dir / STATUS_FILE) or {}).get("wall_time_s", 0.0) if checkpoint is not None else 0.0
    started = time.time()

    def wall_time() -> float:
        """Seconds spent training the run, in all the sessions since its start from step 0."""
        return float(earlier) + time.time() - started

    if checkpoint is not None:  # the logs go back to the checkpoint's step
        for truncate in (logs.truncate_monitor, logs.truncate_progress, logs.truncate_evaluations):
            truncate(run_dir, checkpoint.step)
    else:  # nothing to continue from: start the logs afresh
        for name in (logs.MONITOR_FILE, logs.PROGRESS_FILE, logs.EVALUATIONS_FILE):
            (run_dir / name).unlink(missing_ok=True)
    env = DummyVecEnv([lambda: logs.monitor_env(gym.make(spec.env_id), run_dir)])
    eval_env = DummyVecEnv([lambda: Monitor(gym.make(spec.env_id))])
    try:
        if checkpoint is not None:  # the run goes on exactly where it stopped
            model = load_checkpoint(checkpoint, env, algo_class(spec.algo), device="cpu")
        else:
            model = build_model(spec, env)
        start_step = int(model.num_timesteps)
        model.set_logger(logs.make_logger(run_dir))
        report_status(run_dir, "running", start_step, spec.timesteps, wall_time_s=wall_time())
        callbacks = [_make_callback(spec, run_dir, start_step, wall_time, eval_env)]
        if spec.checkpoint_freq > 0:
            callbacks.append(ResumableCheckpointCallback(spec.checkpoint_freq, str(checkpoints), keep_last=1))
        if start_step < spec.timesteps:
            try:
                model.learn(
                    spec.timesteps - start_step, callback=callbacks, log_interval=1, reset_num_timesteps=checkpoint is None
                )
            except StopTraining:
                pass  # stopped between two rollouts: checkpointed below
        step = int(model.num_timesteps)
        if step < spec.timesteps:
            save_checkpoint(model, checkpoints, keep_last=1)
            report_status(run_dir, "interrupted", step, spec.timesteps, wall_time_s=wall_time())
            return "interrupted", step
        model.save(run_dir / FINAL_MODEL)
    finally:
        env.close()
        eval_env.close()
    done = {"timesteps": step, "episodes": logs.count_episodes(run_dir), "wall_time_s": wall_time()}
    write_json(run_dir / DONE_FILE, {**done, "finished_at": time.time()})
    shutil.rmtree(checkpoints, ignore_errors=True)
    report_status(run_dir, "finished", step, spec.timesteps, wall_time_s=done["wall_time_s"])
    return "finished", step
