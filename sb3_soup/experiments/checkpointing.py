"""
Checkpoints of an off-policy SB3 model (SOUP, TD3, ...) that a run can resume from.

A checkpoint is a folder ``checkpoints/step_{N}`` holding ``model.zip`` (``model.save``), ``replay_buffer.pkl``
(``model.save_replay_buffer``), ``training_state.pkl`` (random generators and environment state) and ``state.json``
(``num_timesteps`` plus whatever the caller adds, e.g. how many Monitor episodes had been written). The files are
written and read by :func:`sb3_soup.checkpoint.save_resumable` and :func:`sb3_soup.checkpoint.load_resumable`, the
mechanism behind :class:`sb3_soup.checkpoint.ResumableCheckpointCallback`; the folder is written under a temporary
name and renamed into place, so a crash while saving never leaves a half-written "latest" checkpoint. Resuming is
``resume(...)`` then ``model.learn(remaining_steps(model, total), reset_num_timesteps=False)``.

Saved between two rollouts (the runner saves from ``_on_rollout_start`` and stops with
:class:`sb3_soup.checkpoint.StopTraining`), a checkpoint resumes exactly: the episode in progress continues and the
random streams go on, so the resumed run is the run that would have happened without the interruption (see
:mod:`sb3_soup.checkpoint` for the limits: DummyVecEnv environments whose state pickles, CPU, same versions).
Checkpoints written before training states existed resume as before: a new episode and a fresh random stream.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import VecEnv

from sb3_soup.checkpoint import StopTraining, load_resumable, save_resumable

__all__ = [
    "Checkpoint",
    "StopTraining",
    "latest_checkpoint",
    "remaining_steps",
    "resume",
    "save_checkpoint",
]

CHECKPOINT_DIR = "checkpoints"
MODEL_FILE = "model.zip"
BUFFER_FILE = "replay_buffer.pkl"
TRAINING_STATE_FILE = "training_state.pkl"
STATE_FILE = "state.json"
_PREFIX = "step_"


@dataclasses.dataclass(frozen=True)
class Checkpoint:
    """
    A saved checkpoint.

    :param path: its folder
    :param step: ``num_timesteps`` when it was taken
    :param state: the contents of its ``state.json``
    """

    path: Path
    step: int
    state: dict[str, Any]

    @property
    def model_path(self) -> Path:
        """The model zip."""
        return self.path / MODEL_FILE

    @property
    def buffer_path(self) -> Path:
        """The pickled replay buffer (absent for on-policy models)."""
        return self.path / BUFFER_FILE

    @property
    def training_state_path(self) -> Path:
        """Random generators and environment state (absent in checkpoints written before they were saved)."""
        return self.path / TRAINING_STATE_FILE


def save_checkpoint(
    model: BaseAlgorithm, run_dir: str | os.PathLike, state: dict[str, Any] | None = None, keep: int = 1
) -> Checkpoint:
    """
    Save the model, its replay buffer, its training state and ``state`` as the run's newest checkpoint, then delete
    all but the ``keep`` newest. Call it between two rollouts (see :func:`sb3_soup.checkpoint.save_training_state`).

    :param model: the model
    :param run_dir: the run's folder (checkpoints go to ``run_dir/checkpoints``)
    :param state: extra JSON-serialisable state to store with it
    :param keep: how many checkpoints to keep (at least 1)
    :return: the new checkpoint
    """
    root = Path(run_dir) / CHECKPOINT_DIR
    root.mkdir(parents=True, exist_ok=True)
    step = int(model.num_timesteps)
    full_state = {**(state or {}), "num_timesteps": step}
    tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=root))
    try:
        save_resumable(model, tmp / MODEL_FILE, tmp / BUFFER_FILE, tmp / TRAINING_STATE_FILE)
        (tmp / STATE_FILE).write_text(json.dumps(full_state, indent=2, sort_keys=True))
        final = root / f"{_PREFIX}{step:012d}"
        if final.exists():
            shutil.rmtree(final)
        tmp.rename(final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    for old in _checkpoint_dirs(root)[: -max(1, keep)]:
        shutil.rmtree(old, ignore_errors=True)
    return Checkpoint(final, step, full_state)


def _checkpoint_dirs(root: Path) -> list[Path]:
    """Complete checkpoint folders under ``root``, oldest first."""
    if not root.is_dir():
        return []
    found = [path for path in root.iterdir() if path.name.startswith(_PREFIX) and (path / STATE_FILE).is_file()]
    return sorted(found, key=lambda path: int(path.name[len(_PREFIX) :]))


def latest_checkpoint(run_dir: str | os.PathLike) -> Checkpoint | None:
    """
    :param run_dir: the run's folder
    :return: its newest complete checkpoint, or ``None``
    """
    dirs = _checkpoint_dirs(Path(run_dir) / CHECKPOINT_DIR)
    if not dirs:
        return None
    state = json.loads((dirs[-1] / STATE_FILE).read_text())
    return Checkpoint(dirs[-1], int(state["num_timesteps"]), state)


def resume(
    checkpoint: Checkpoint,
    algo_class: type[BaseAlgorithm],
    env: VecEnv,
    fallback_seed: int | None = None,
    **load_kwargs: Any,
) -> BaseAlgorithm:
    """
    Load a checkpoint (:func:`sb3_soup.checkpoint.load_resumable`): the model, its replay buffer, the random
    generators and the environment's state, which ``env`` takes.

    :param checkpoint: from :func:`latest_checkpoint`
    :param algo_class: the model's class (``SOUP``, ``TD3``, ...)
    :param env: the environment to continue on, built as the saved one
    :param fallback_seed: for a checkpoint without training state (written by an older version): reseed with it, so
        that the continuation does not replay the run's first random numbers
    :param load_kwargs: passed to ``algo_class.load`` (e.g. ``device``, ``custom_objects``)
    :return: the model, ready for ``learn(remaining_steps(model, total), reset_num_timesteps=False)``
    """
    has_state = checkpoint.training_state_path.is_file()
    model = load_resumable(
        algo_class,
        checkpoint.model_path,
        env,
        checkpoint.buffer_path if checkpoint.buffer_path.is_file() else None,
        checkpoint.training_state_path if has_state else None,
        **load_kwargs,
    )
    if not has_state and fallback_seed is not None:
        model.set_random_seed(fallback_seed)
    return model


def remaining_steps(model: BaseAlgorithm, total_timesteps: int) -> int:
    """
    :param model: a (resumed) model
    :param total_timesteps: the run's total steps
    :return: the steps still to do
    """
    return max(0, int(total_timesteps) - int(model.num_timesteps))
