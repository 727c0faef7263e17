"""
Checkpoints a run resumes from exactly: after a crash, a kill or a planned stop, loading the last checkpoint and calling
``learn(remaining, reset_num_timesteps=False)`` gives the same actions and the same parameters as a run that was never
interrupted (on CPU, same library versions and thread count).

A checkpoint is four files, written by :class:`ResumableCheckpointCallback` (or :func:`save_checkpoint`,
:func:`save_resumable`), each atomically (:func:`sb3_soup.persistence.atomic_write`) and the model zip last, so that
a checkpoint, found by its zip, is complete or absent:

- the replay buffer with its bootstrap masks (``model.save_replay_buffer``),
- optionally the ``VecNormalize`` statistics, as SB3 saves them,
- the training state: the environment's state (:func:`sb3_soup.persistence.get_env_state`: every layer of a
  ``DummyVecEnv``, down to the simulator) and, for algorithms other than SOUP, the random generators' states,
- the model zip (``model.save``: networks, optimizers, strategy state, step counters, last observation, the active
  head pairs; for SOUP also the random generators' states, which ``SOUP.load`` restores).

Why SB3's own ``CheckpointCallback`` cannot give this: it saves inside a step (after ``env.step``, before the
transition is stored and the model trained), so its files disagree with each other (the environment is one step ahead
of the model's last observation, the buffer one transition short), and it saves neither the random generators nor the
environment. SB3's ``load`` then resets the environment (``force_reset=True``) and reseeds the generators with the
model's seed: a faithful continuation, not the same run. :class:`ResumableCheckpointCallback` saves between two
rollouts instead, where everything agrees, with the same arguments and file names.

What stays inexact, and why:

- the environment state is restored for ``DummyVecEnv`` environments whose layers pickle (pure-Python and MuJoCo
  envs do; a ``SubprocVecEnv``'s envs live in other processes, a renderer's window does not pickle): otherwise the
  checkpoint is saved without it (with a warning) and the resumed run starts new episodes;
- SB3 calls ``action_noise.reset()`` when ``learn`` starts: an ``OrnsteinUhlenbeckActionNoise`` restarts from zero
  (SOUP's built-in Gaussian noise and ``NormalActionNoise`` have no state);
- callbacks other than this one start afresh (e.g. ``EvalCallback`` counts its calls from 0);
- other thread counts, devices (GPU kernels are not bit-reproducible) or library versions change the floating point.
"""

import dataclasses
import os
import pickle
import pickletools
import re
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import CheckpointCallback
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import GymEnv
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecNormalize, unwrap_vec_normalize

from sb3_soup.persistence import (
    TMP_MARK,
    EnvStateError,
    atomic_write,
    capture_rng_state,
    get_env_state,
    restore_rng_state,
    set_env_state,
)
from sb3_soup.soup import SOUP

TRAINING_STATE_FORMAT = 2
"""Format of the training-state files this version writes and reads (2: the random generators only when the model zip
does not hold them)."""


class StopTraining(Exception):
    """
    Raise it from a callback's ``_on_rollout_start`` to leave ``learn`` between two rollouts, where a checkpoint
    is consistent (returning ``False`` from ``_on_step`` stops in the middle of a step). Catch it around ``learn``.
    """


# ---------------------------------------------------------------- training state (environment + random generators)


def _check_at_boundary(model: BaseAlgorithm, vec_env: VecEnv) -> None:
    """For a plain DummyVecEnv: refuse a state taken mid-step (the env's observation is not the model's last one)."""
    if isinstance(vec_env, DummyVecEnv):
        current = vec_env._obs_from_buf()
        last = model._last_obs
        same = (
            all(np.array_equal(current[key], last[key]) for key in current)  # type: ignore[index]
            if isinstance(current, dict) and isinstance(last, dict)
            else np.array_equal(current, last)  # type: ignore[arg-type]
        )
        if not same:
            raise EnvStateError(
                "the environment has stepped past the model's last observation (saved in the middle of a step, e.g. from "
                "a callback's _on_step): save from _on_rollout_start or after learn() returned"
            )


def _dump_pickle(data: Any) -> Callable[[Path], None]:
    def write(path: Path) -> None:
        with open(path, "wb") as file:
            pickle.dump(data, file, protocol=pickle.HIGHEST_PROTOCOL)

    return write


def _zip_holds_rng_state(model: BaseAlgorithm) -> bool:
    """Whether ``model.save`` stores the random generators' states (``SOUP.save`` does, and ``SOUP.load`` restores them)."""
    return isinstance(model, SOUP)


def save_training_state(model: BaseAlgorithm, path: str | os.PathLike) -> bool:
    """
    Save what ``model.save`` and ``model.save_replay_buffer`` leave out: the environment's state and, for algorithms
    whose model zip does not hold them (all but SOUP), the random generators' states. Call it between two rollouts
    (from a callback's ``_on_rollout_start``, or after ``learn`` returned), where the model and its environment agree.

    :param model: the model (any SB3 algorithm)
    :param path: the file to write (atomically)
    :return: whether the environment's state is in it (if not, a warning says why, and a resumed run starts new episodes)
    """
    env_state, reason = None, None
    vec_env = model.get_env()
    if vec_env is not None and model._last_obs is not None:
        try:
            _check_at_boundary(model, vec_env)
            env_state = get_env_state(vec_env)
        except EnvStateError as error:
            reason = str(error)
            warnings.warn(
                f"checkpoint without the environment's state ({reason}): a run resumed from it starts new episodes, "
                "it is not an exact continuation",
                UserWarning,
                stacklevel=2,
            )
    state = {
        "format": TRAINING_STATE_FORMAT,
        "num_timesteps": int(model.num_timesteps),
        "rng": None if _zip_holds_rng_state(model) else capture_rng_state(model.action_space),
        "env": env_state,
        "env_missing_because": reason,
    }
    atomic_write(path, _dump_pickle(state))
    return env_state is not None


def read_training_state(path: str | os.PathLike) -> dict[str, Any]:
    """
    :param path: a file written by :func:`save_training_state`
    :return: its content
    """
    try:
        with open(path, "rb") as file:
            state = pickle.load(file)
    except OSError:
        raise
    except Exception as error:
        raise ValueError(f"could not read the training state {path}: truncated or corrupt ({error})") from error
    if not isinstance(state, dict) or state.get("format") != TRAINING_STATE_FORMAT:
        found = state.get("format") if isinstance(state, dict) else type(state).__name__
        raise ValueError(
            f"{path} is not a training state this sb3-soup reads (format {found!r}, expected {TRAINING_STATE_FORMAT})"
        )
    return state


def restore_training_state(model: BaseAlgorithm, state: dict[str, Any], path: Any = "training state") -> bool:
    """
    Restore the random generators (when the training state holds them) and, when it was saved and the model kept its
    last observation (``load(..., force_reset=False)``), the environment.

    :param model: the loaded model, with its environment
    :param state: from :func:`read_training_state`
    :param path: where it came from, for the messages
    :return: whether the environment was restored
    """
    if state["num_timesteps"] != model.num_timesteps:
        raise ValueError(
            f"{path} was saved at step {state['num_timesteps']} but the model is at step {model.num_timesteps}: "
            "files from different checkpoints"
        )
    if state["rng"] is not None:
        restore_rng_state(state["rng"], model.action_space)
    vec_env = model.get_env()
    if state["env"] is None or vec_env is None or model._last_obs is None:
        return False
    set_env_state(vec_env, state["env"])
    return True


# ---------------------------------------------------------------- whole checkpoints


def save_resumable(
    model: BaseAlgorithm,
    model_path: str | os.PathLike,
    replay_buffer_path: str | os.PathLike | None = None,
    training_state_path: str | os.PathLike | None = None,
    vecnormalize_path: str | os.PathLike | None = None,
) -> bool:
    """
    Save a checkpoint: each file written atomically, the model zip last (a checkpoint is found by its zip, so its
    presence means the checkpoint is complete). Call it between two rollouts (see :func:`save_training_state`).

    :param model: the model
    :param model_path: its zip
    :param replay_buffer_path: its replay buffer (off-policy models), or None
    :param training_state_path: the environment (and the random generators, see :func:`save_training_state`), or None
    :param vecnormalize_path: the ``VecNormalize`` statistics (when the env has them), or None
    :return: whether the checkpoint holds the environment's state (an exact resume)
    """
    if replay_buffer_path is not None and isinstance(model, OffPolicyAlgorithm) and model.replay_buffer is not None:
        atomic_write(replay_buffer_path, model.save_replay_buffer)
    vec_normalize = model.get_vec_normalize_env()
    if vecnormalize_path is not None and vec_normalize is not None:
        atomic_write(vecnormalize_path, lambda path: vec_normalize.save(str(path)))
    exact = training_state_path is not None and save_training_state(model, training_state_path)
    atomic_write(model_path, model.save)
    return exact


def load_resumable(
    algo_class: type[BaseAlgorithm],
    model_path: str | os.PathLike,
    env: GymEnv | None,
    replay_buffer_path: str | os.PathLike | None = None,
    training_state_path: str | os.PathLike | None = None,
    **load_kwargs: Any,
) -> BaseAlgorithm:
    """
    Load a checkpoint saved by :func:`save_resumable`: the model, its replay buffer, the random generators and the
    environment's state. Continue with ``model.learn(remaining, reset_num_timesteps=False)``.

    :param algo_class: the model's class (``SOUP``, ``TD3``...)
    :param model_path: the model zip
    :param env: an environment built as the saved one (its state is overwritten with the saved state)
    :param replay_buffer_path: the replay buffer, or None
    :param training_state_path: the training state, or None (then the environment is reset, as SB3 does)
    :param load_kwargs: passed to ``algo_class.load`` (``device``, ``custom_objects``...)
    :return: the model
    """
    state = read_training_state(training_state_path) if training_state_path is not None else None
    exact = state is not None and state["env"] is not None and env is not None
    model = algo_class.load(Path(model_path), env=env, force_reset=not exact, **load_kwargs)
    if replay_buffer_path is not None and isinstance(model, OffPolicyAlgorithm):
        model.load_replay_buffer(Path(replay_buffer_path))
    if state is not None:
        restore_training_state(model, state, training_state_path)
    return model


@dataclasses.dataclass(frozen=True)
class CheckpointFiles:
    """
    The files of one checkpoint in a folder written by SB3's ``CheckpointCallback`` or :class:`ResumableCheckpointCallback`.

    :param step: ``num_timesteps`` when it was saved
    :param model: the model zip
    :param replay_buffer: the replay buffer, if saved
    :param training_state: the training state (environment, random generators), if saved
    :param vecnormalize: the ``VecNormalize`` statistics, if saved
    """

    step: int
    model: Path
    replay_buffer: Path | None
    training_state: Path | None
    vecnormalize: Path | None

    @property
    def paths(self) -> list[Path]:
        """Its files."""
        return [path for path in (self.model, self.replay_buffer, self.training_state, self.vecnormalize) if path]


def _file(save_path: Path, name_prefix: str, kind: str, step: int, extension: str) -> Path:
    return save_path / f"{name_prefix}_{kind}{step}_steps.{extension}"


def find_checkpoints(save_path: str | os.PathLike, name_prefix: str = "rl_model") -> list[CheckpointFiles]:
    """
    :param save_path: the checkpoint folder
    :param name_prefix: the callback's ``name_prefix``
    :return: its checkpoints, newest first (complete or not)
    """
    root = Path(save_path)
    if not root.is_dir():
        return []
    pattern = re.compile(rf"{re.escape(name_prefix)}_(\d+)_steps\.zip")
    found = []
    for path in root.iterdir():
        match = pattern.fullmatch(path.name)
        if match:
            step = int(match.group(1))

            def optional(kind: str, step: int = step) -> Path | None:
                candidate = _file(root, name_prefix, kind, step, "pkl")
                return candidate if candidate.is_file() else None

            found.append(
                CheckpointFiles(step, path, optional("replay_buffer_"), optional("training_state_"), optional("vecnormalize_"))
            )
    return sorted(found, key=lambda checkpoint: checkpoint.step, reverse=True)


def _complete_pickle(path: Path) -> bool:
    """Whether a pickle file is complete (its opcodes parse to the STOP at its end), without building its objects."""
    try:
        with open(path, "rb") as file:
            for _ in pickletools.genops(file):
                pass
            return file.read(1) == b""
    except Exception:
        return False


def _complete_zip(path: Path) -> bool:
    try:
        with zipfile.ZipFile(path) as archive:
            return "data" in archive.namelist() and archive.testzip() is None
    except (zipfile.BadZipFile, OSError, EOFError):
        return False


def is_complete(checkpoint: CheckpointFiles) -> bool:
    """
    Whether every file of a checkpoint is whole: for SB3's ``CheckpointCallback``, which writes in place, a kill while
    saving leaves a truncated zip or pickle (:class:`ResumableCheckpointCallback` writes atomically).

    :param checkpoint: from :func:`find_checkpoints`
    """
    if not _complete_zip(checkpoint.model):
        return False
    return all(_complete_pickle(path) for path in (checkpoint.replay_buffer, checkpoint.training_state) if path is not None)


def latest_checkpoint(
    save_path: str | os.PathLike, name_prefix: str = "rl_model", need_replay_buffer: bool = True
) -> CheckpointFiles | None:
    """
    The newest complete checkpoint of a folder (truncated files from a kill while saving are skipped).

    :param save_path: the checkpoint folder
    :param name_prefix: the callback's ``name_prefix``
    :param need_replay_buffer: skip checkpoints without a replay buffer
    :return: the checkpoint, or None
    """
    for checkpoint in find_checkpoints(save_path, name_prefix):
        if (checkpoint.replay_buffer is not None or not need_replay_buffer) and is_complete(checkpoint):
            return checkpoint
    return None


def load_checkpoint(
    checkpoint: CheckpointFiles, env: GymEnv | None, algo_class: type[BaseAlgorithm] | None = None, **load_kwargs: Any
) -> BaseAlgorithm:
    """
    Load a checkpoint (see :func:`load_resumable`); continue with ``learn(remaining, reset_num_timesteps=False)``.
    From SB3's ``CheckpointCallback`` (no training state) the environment is reset (a faithful continuation).

    :param checkpoint: from :func:`latest_checkpoint`
    :param env: an environment built as the saved one
    :param algo_class: the model's class (default: SOUP)
    :param load_kwargs: passed to ``algo_class.load``
    :return: the model
    """
    if algo_class is None:
        algo_class = SOUP
    if checkpoint.vecnormalize is not None and isinstance(env, VecEnv) and unwrap_vec_normalize(env) is None:
        env = VecNormalize.load(str(checkpoint.vecnormalize), env)
    return load_resumable(
        algo_class, checkpoint.model, env, checkpoint.replay_buffer, checkpoint.training_state, **load_kwargs
    )


def save_checkpoint(
    model: BaseAlgorithm,
    save_path: str | os.PathLike,
    name_prefix: str = "rl_model",
    save_replay_buffer: bool = True,
    save_vecnormalize: bool = False,
    keep_last: int | None = None,
) -> CheckpointFiles:
    """
    Save a checkpoint now, as :class:`ResumableCheckpointCallback` does every ``save_freq`` steps (same files, see
    :func:`save_resumable`), then delete the older ones beyond ``keep_last``. Call it between two rollouts (e.g. after
    ``learn`` returned or :class:`StopTraining` stopped it).

    :param model: the model
    :param save_path: the checkpoint folder
    :param name_prefix: common prefix of the files
    :param save_replay_buffer: save the replay buffer too (needed to resume)
    :param save_vecnormalize: save the ``VecNormalize`` statistics too, as SB3 does
    :param keep_last: keep only the newest ``keep_last`` checkpoints (None: keep all)
    :return: the checkpoint's files
    """
    step = int(model.num_timesteps)
    root = Path(save_path)
    files = CheckpointFiles(
        step,
        _file(root, name_prefix, "", step, "zip"),
        _file(root, name_prefix, "replay_buffer_", step, "pkl") if save_replay_buffer else None,
        _file(root, name_prefix, "training_state_", step, "pkl"),
        _file(root, name_prefix, "vecnormalize_", step, "pkl") if save_vecnormalize else None,
    )
    save_resumable(model, files.model, files.replay_buffer, files.training_state, files.vecnormalize)
    if keep_last is not None:
        for old in find_checkpoints(root, name_prefix)[keep_last:]:
            for path in old.paths:  # the zip first: the checkpoint is gone at once
                path.unlink(missing_ok=True)
    return files


def _remove_leftovers(save_path: Path, name_prefix: str) -> None:
    """What a process killed while saving left: temporary files, and the files of a checkpoint without its zip."""
    for stale in save_path.glob(f".{name_prefix}_*{TMP_MARK}*"):
        stale.unlink(missing_ok=True)
    pattern = re.compile(rf"{re.escape(name_prefix)}_(?:replay_buffer|training_state|vecnormalize)_(\d+)_steps\.pkl")
    for path in save_path.iterdir():
        match = pattern.fullmatch(path.name)
        if match and not _file(save_path, name_prefix, "", int(match.group(1)), "zip").exists():
            path.unlink(missing_ok=True)


class ResumableCheckpointCallback(CheckpointCallback):
    """
    SB3's ``CheckpointCallback`` (same arguments, same file names) whose checkpoints resume exactly
    (see :mod:`sb3_soup.checkpoint`): it saves between two rollouts, every ``save_freq`` calls to ``env.step()``
    counted from the run's start (so a resumed run keeps the schedule), adds
    ``{name_prefix}_training_state_{N}_steps.pkl``, writes each file atomically (the model zip last), clears what a
    process killed while saving left, and can delete old checkpoints. Resume with :func:`latest_checkpoint` and
    :func:`load_checkpoint`.

    :param save_freq: save every ``save_freq`` calls to ``env.step()`` (``save_freq * n_envs`` steps)
    :param save_path: the checkpoint folder
    :param name_prefix: common prefix of the files
    :param save_replay_buffer: save the replay buffer too (needed to resume; True by default, unlike SB3)
    :param save_vecnormalize: save the ``VecNormalize`` statistics too, as SB3 does (they are also in the training state)
    :param keep_last: keep only the newest ``keep_last`` checkpoints (None: keep all)
    :param verbose: 2 prints each save
    """

    def __init__(
        self,
        save_freq: int,
        save_path: str,
        name_prefix: str = "rl_model",
        save_replay_buffer: bool = True,
        save_vecnormalize: bool = False,
        keep_last: int | None = None,
        verbose: int = 0,
    ):
        super().__init__(save_freq, save_path, name_prefix, save_replay_buffer, save_vecnormalize, verbose)
        if not isinstance(save_freq, int) or save_freq < 1:
            raise ValueError(f"save_freq must be an integer >= 1 (calls to env.step() between checkpoints), got {save_freq!r}")
        if keep_last is not None and (not isinstance(keep_last, int) or keep_last < 1):
            raise ValueError(f"keep_last must be None (keep all) or an integer >= 1, got {keep_last!r}")
        self.keep_last = keep_last
        self.last_saved = 0

    def _init_callback(self) -> None:
        super()._init_callback()
        self.last_saved = int(self.model.num_timesteps)
        _remove_leftovers(Path(self.save_path), self.name_prefix)

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        period = self.save_freq * self.model.n_envs
        if self.model.num_timesteps // period > self.last_saved // period:
            self.save()

    def save(self) -> CheckpointFiles:
        """Save a checkpoint now (call it between two rollouts)."""
        files = save_checkpoint(
            self.model, self.save_path, self.name_prefix, self.save_replay_buffer, self.save_vecnormalize, self.keep_last
        )
        self.last_saved = files.step
        if self.verbose >= 2:
            print(f"Saving resumable checkpoint {files.model}")
        return files
