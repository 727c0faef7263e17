"""
Saving and resuming runs, for any SB3 algorithm (SOUP, TD3, DDPG, SAC...). After a crash, a kill or a planned stop,
loading the last checkpoint and calling ``learn(remaining, reset_num_timesteps=False)`` gives the same actions and the
same parameters as a run that was never interrupted (on CPU, same library versions and thread count).

A checkpoint is up to four files, written by :class:`ResumableCheckpointCallback` or :func:`save_checkpoint`, each
atomically (:func:`atomic_write`) and the model zip last, so that a checkpoint, found by its zip, is complete or absent:

- the replay buffer (``model.save_replay_buffer``; SOUP's holds the bootstrap masks),
- optionally the ``VecNormalize`` statistics, as SB3 saves them,
- the training state (:func:`save_training_state`): the random generators' states (:func:`capture_rng_state`) and the
  environment's state (:func:`get_env_state`: every layer of a ``DummyVecEnv``, down to the simulator),
- the model zip (``model.save``, SB3's: networks, optimizers, step counters, last observation; for SOUP also the
  confidence strategy's state and the active head pairs).

``model.save`` and ``load`` stay SB3's: ``load`` resets the environment (``force_reset=True``) and reseeds the random
generators with the model's seed, a faithful continuation but not the same run; :func:`load_checkpoint` puts the
generators and the environment back as they were. SB3's own ``CheckpointCallback`` cannot give this either: it saves
inside a step (after ``env.step``, before the transition is stored and the model trained), so its files disagree with
each other (the environment is one step ahead of the model's last observation, the buffer one transition short), and
it saves neither the random generators nor the environment. :class:`ResumableCheckpointCallback` saves between two
rollouts instead, where everything agrees, with the same arguments and file names. What stays inexact (a
``SubprocVecEnv``, an env that does not pickle, ``OrnsteinUhlenbeckActionNoise``, other callbacks, other hardware or
versions), and why: docs/reliability.md.
"""

import copy
import dataclasses
import io
import json
import os
import pickle
import pickletools
import random
import re
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cloudpickle
import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import CheckpointCallback
from stable_baselines3.common.monitor import ResultsWriter
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.save_util import open_path
from stable_baselines3.common.type_aliases import GymEnv
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecEnvWrapper, VecNormalize, unwrap_vec_normalize

TMP_MARK = ".tmp-"
"""In the names of :func:`atomic_write`'s temporary files: ``.{name}.tmp-{pid}``, next to the file being written."""

TRAINING_STATE_FORMAT = 3
"""Format of the training-state files this version writes and reads (3: the random generators for every algorithm)."""

_ZIP_MAGIC = b"PK\x03\x04"

# Live objects that stay with the running environment (open log files): never saved, never replaced
_KEPT_LIVE: tuple[type, ...] = (ResultsWriter, io.IOBase)


class StopTraining(Exception):
    """
    Raise it from a callback's ``_on_rollout_start`` to leave ``learn`` between two rollouts, where a checkpoint
    is consistent (returning ``False`` from ``_on_step`` stops in the middle of a step). Catch it around ``learn``.
    """


# ---------------------------------------------------------------- files: atomic writes, model zips


def atomic_write(path: str | os.PathLike, write: Callable[[Path], Any]) -> None:
    """
    Write a file atomically: ``write(tmp)``, an fsync, then ``tmp`` renamed to ``path``. ``path`` is the whole new
    file or what it was before, never a part (a temporary file left by a kill is named ``.{name}.tmp-{pid}``).

    :param path: the file
    :param write: writes the content to the path it is given (e.g. ``model.save``, ``Path.write_text``)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}{TMP_MARK}{os.getpid()}")
    try:
        write(tmp)
        with open(tmp, "rb+") as file:
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def read_model_data(path: str | Path | io.BufferedIOBase) -> dict[str, Any]:
    """
    Check a model zip written by ``model.save`` (any SB3 algorithm) and read its ``data`` entry as JSON, unpickling
    nothing, with a clear error for a file that is not a model zip, a truncated one (a process killed while writing it)
    or a corrupt one (the CRC of every entry is checked).

    :param path: the model file (``.zip`` may be left out, as with SB3's ``load``) or an open binary file (left where
        it was found, for SB3's ``load`` to read it)
    :return: the saved attributes; pickled ones are left as SB3 stores them (dicts with ``:serialized:``)
    :raises ValueError: for a file that is not a complete model zip
    """
    file = open_path(path, "r", suffix="zip")
    start = file.tell()
    name = str(path) if isinstance(path, (str, os.PathLike)) else f"<{type(path).__name__}>"
    advice = "load an earlier checkpoint (sb3_soup.checkpoint.latest_checkpoint finds the newest complete one)"
    truncated = f"{name} is a truncated or corrupt model zip ({{}}): a process killed while saving leaves such files; {advice}"
    try:
        head = file.read(64)
        file.seek(start)
        try:
            archive = zipfile.ZipFile(file)
        except (zipfile.BadZipFile, EOFError) as error:
            if head[:4] == _ZIP_MAGIC:
                raise ValueError(truncated.format(error)) from error
            raise ValueError(
                f"{name} is not a saved model: it is not a zip archive (model.save writes a .zip; replay buffers are "
                "loaded with model.load_replay_buffer)"
            ) from error
        with archive:
            if "data" not in archive.namelist():
                # SB3 writes the 'data' entry first: a zip that starts with it but does not list it was cut short (the
                # zip reader then finds the directory of policy.pth, itself a zip, inside the remains)
                if head[:4] == _ZIP_MAGIC and head[30 : 30 + int.from_bytes(head[26:28], "little")] == b"data":
                    raise ValueError(truncated.format("its directory has no 'data' entry"))
                raise ValueError(
                    f"{name} is a zip archive but not a saved model: it has no 'data' entry (SB3's model.save writes "
                    "data, policy.pth and the optimizers' .pth files)"
                )
            try:
                for entry in archive.namelist():
                    with archive.open(entry) as content:
                        while content.read(1 << 20):  # to its end: the CRC is checked there
                            pass
            except (zipfile.BadZipFile, EOFError) as error:
                raise ValueError(f"{name} is a corrupt model zip ({error}): {advice}") from error
            raw = archive.read("data")
    finally:
        if isinstance(path, (str, os.PathLike)):
            file.close()
        else:
            file.seek(start)
    try:
        data = json.loads(raw)
    except ValueError as error:
        raise ValueError(f"{name} is a corrupt model zip: its 'data' entry is not valid JSON ({error})") from error
    if not isinstance(data, dict):
        raise ValueError(f"{name} is not a saved model: its 'data' entry holds {type(data).__name__}, not a dict")
    return data


# ---------------------------------------------------------------- random generators


def capture_rng_state(action_space: Any = None) -> dict[str, Any]:
    """
    The states of the random generators a training run draws from: Python's ``random``, NumPy's global generator,
    torch's CPU and (when in use) CUDA generators.

    :param action_space: also keep this gymnasium space's generator (SB3 samples warm-up actions from it)
    :return: a picklable dict for :func:`restore_rng_state`
    """
    state: dict[str, Any] = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": th.get_rng_state()}
    if th.cuda.is_available() and th.cuda.is_initialized():
        state["torch_cuda"] = th.cuda.get_rng_state_all()
    if action_space is not None:
        state["action_space"] = copy.deepcopy(getattr(action_space, "_np_random", None))
    return state


def restore_rng_state(state: dict[str, Any], action_space: Any = None) -> None:
    """
    Put the random generators back in the state :func:`capture_rng_state` returned.

    :param state: the captured state
    :param action_space: restore this space's generator too (when it was captured)
    """
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    th.set_rng_state(state["torch"])
    cuda_states = state.get("torch_cuda")
    if cuda_states is not None and th.cuda.is_available() and th.cuda.device_count() == len(cuda_states):
        th.cuda.set_rng_state_all(cuda_states)
    if action_space is not None and state.get("action_space") is not None:
        action_space._np_random = copy.deepcopy(state["action_space"])


# ---------------------------------------------------------------- environment state


class EnvStateError(Exception):
    """The environment's state cannot be saved (or restored into this environment)."""


def _qualified_name(obj: Any) -> str:
    return f"{type(obj).__module__}.{type(obj).__qualname__}"


def _vec_layers(vec_env: VecEnv) -> list[VecEnv]:
    """The VecEnv wrappers, outermost first, then the base VecEnv."""
    layers = [vec_env]
    while isinstance(layers[-1], VecEnvWrapper):
        layers.append(layers[-1].venv)
    return layers


def _env_layers(env: gym.Env) -> list[Any]:
    """The gymnasium wrappers of a sub-environment, outermost first, then the unwrapped env."""
    layers = [env]
    while isinstance(layers[-1], gym.Wrapper):
        layers.append(layers[-1].env)
    return layers


def _layer_state(layer: Any, links: tuple[str, ...]) -> dict[str, Any]:
    """A layer's attributes, without its links to the layers below and without live log files."""
    return {key: value for key, value in vars(layer).items() if key not in links and not isinstance(value, _KEPT_LIVE)}


def _structure(vec_env: VecEnv) -> dict[str, Any]:
    layers = _vec_layers(vec_env)
    base = layers[-1]
    envs = base.envs if isinstance(base, DummyVecEnv) else []
    return {
        "vec_layers": [_qualified_name(layer) for layer in layers],
        "envs": [[_qualified_name(layer) for layer in _env_layers(env)] for env in envs],
    }


def get_env_state(vec_env: VecEnv) -> bytes:
    """
    The state of a ``DummyVecEnv`` (and of the VecEnv wrappers around it): every attribute of every layer, down to
    each sub-environment's simulator, pickled (open log files such as ``Monitor``'s are left out).

    Layers are saved attribute by attribute, not through their own pickling, which some envs restrict to their
    constructor arguments (gymnasium's ``EzPickle``, used by MuJoCo envs, would lose the simulator state).

    :param vec_env: the environment
    :return: the state, for :func:`set_env_state`
    :raises EnvStateError: when it is not a ``DummyVecEnv`` or a layer does not pickle
    """
    layers = _vec_layers(vec_env)
    base = layers[-1]
    if not isinstance(base, DummyVecEnv):
        raise EnvStateError(
            f"only DummyVecEnv environments can be saved (their envs live in this process), not {type(base).__name__}"
        )
    state = {
        "structure": _structure(vec_env),
        "vec_layers": [_layer_state(layer, ("venv", "class_attributes")) for layer in layers[:-1]],
        "base": _layer_state(base, ("envs",)),
        "envs": [[_layer_state(layer, ("env",)) for layer in _env_layers(env)] for env in base.envs],
    }
    try:
        return cloudpickle.dumps(state)
    except Exception as error:
        raise EnvStateError(f"the environment's state does not pickle: {type(error).__name__}: {error}") from error


def set_env_state(vec_env: VecEnv, env_state: bytes) -> None:
    """
    Put an environment back in a state saved by :func:`get_env_state`. It must be built the same way (same wrappers,
    same number of envs); live log files (``Monitor``'s) stay those of ``vec_env``.

    :param vec_env: the environment, e.g. freshly made
    :param env_state: from :func:`get_env_state`
    :raises EnvStateError: when ``vec_env`` is not built like the saved one
    """
    state = pickle.loads(env_state)
    structure = _structure(vec_env)
    if structure != state["structure"]:
        raise EnvStateError(
            f"the environment is not built like the saved one: saved {state['structure']}, given {structure} "
            "(VecEnv wrappers outermost first, then each env's wrappers)"
        )
    layers = _vec_layers(vec_env)
    for layer, saved in zip(layers[:-1], state["vec_layers"]):
        vars(layer).update(saved)
    base = layers[-1]
    assert isinstance(base, DummyVecEnv)
    vars(base).update(state["base"])
    for env, saved_layers in zip(base.envs, state["envs"]):
        for layer, saved in zip(_env_layers(env), saved_layers):
            vars(layer).update(saved)


# ---------------------------------------------------------------- training state (random generators + environment)


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


def save_training_state(model: BaseAlgorithm, path: str | os.PathLike) -> bool:
    """
    Save what ``model.save`` and ``model.save_replay_buffer`` leave out: the random generators' states and the
    environment's state. Call it between two rollouts (from a callback's ``_on_rollout_start``, or after ``learn``
    returned), where the model and its environment agree.

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
        "rng": capture_rng_state(model.action_space),
        "env": env_state,
        "env_missing_because": reason,
    }

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as file:
            pickle.dump(state, file, protocol=pickle.HIGHEST_PROTOCOL)

    atomic_write(path, write)
    return env_state is not None


def read_training_state(path: str | os.PathLike) -> dict[str, Any]:
    """
    :param path: a file written by :func:`save_training_state`
    :return: its content
    :raises ValueError: for a truncated or corrupt file, or one of another format
    """
    try:
        with open(path, "rb") as file:
            state = pickle.load(file)
    except OSError:
        raise
    except Exception as error:
        raise ValueError(f"could not read the training state {path}: truncated or corrupt ({error})") from error
    found = state.get("format") if isinstance(state, dict) else type(state).__name__
    if found != TRAINING_STATE_FORMAT:
        raise ValueError(
            f"{path} is a training state of format {found!r}, written by another sb3-soup; this one reads format "
            f"{TRAINING_STATE_FORMAT}: resume the checkpoint with the sb3-soup that wrote it, or load its model zip alone "
            "(algo.load and load_replay_buffer: a faithful continuation, with new episodes and reseeded generators)"
        )
    return state


def restore_training_state(model: BaseAlgorithm, state: dict[str, Any], path: Any = "training state") -> bool:
    """
    Restore the random generators and, when it was saved and the model kept its last observation
    (``load(..., force_reset=False)``), the environment.

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
    restore_rng_state(state["rng"], model.action_space)
    vec_env = model.get_env()
    if state["env"] is None or vec_env is None or model._last_obs is None:
        return False
    set_env_state(vec_env, state["env"])
    return True


# ---------------------------------------------------------------- checkpoints


@dataclasses.dataclass(frozen=True)
class CheckpointFiles:
    """
    The files of one checkpoint, e.g. in a folder written by SB3's ``CheckpointCallback`` or
    :class:`ResumableCheckpointCallback` (:func:`find_checkpoints`).

    :param step: ``num_timesteps`` when it was saved
    :param model: the model zip
    :param replay_buffer: the replay buffer, if saved
    :param training_state: the training state (random generators, environment), if saved
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


def is_complete(checkpoint: CheckpointFiles) -> bool:
    """
    Whether every file of a checkpoint is whole: for SB3's ``CheckpointCallback``, which writes in place, a kill while
    saving leaves a truncated zip or pickle (:class:`ResumableCheckpointCallback` writes atomically).

    :param checkpoint: from :func:`find_checkpoints`
    """
    try:
        read_model_data(checkpoint.model)
    except (ValueError, OSError):
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
    :mod:`sb3_soup.checkpoint`), each file atomically and the model zip last, then delete the older ones beyond
    ``keep_last``. Call it between two rollouts (e.g. after ``learn`` returned or :class:`StopTraining` stopped it).

    :param model: the model
    :param save_path: the checkpoint folder
    :param name_prefix: common prefix of the files
    :param save_replay_buffer: save the replay buffer too (off-policy models; needed to resume)
    :param save_vecnormalize: save the ``VecNormalize`` statistics too (when the env has them), as SB3 does
    :param keep_last: keep only the newest ``keep_last`` checkpoints (None: keep all)
    :return: the checkpoint's files
    """
    step = int(model.num_timesteps)
    root = Path(save_path)
    has_buffer = isinstance(model, OffPolicyAlgorithm) and model.replay_buffer is not None
    vec_normalize = model.get_vec_normalize_env()
    training_state = _file(root, name_prefix, "training_state_", step, "pkl")
    files = CheckpointFiles(
        step,
        _file(root, name_prefix, "", step, "zip"),
        _file(root, name_prefix, "replay_buffer_", step, "pkl") if save_replay_buffer and has_buffer else None,
        training_state,
        _file(root, name_prefix, "vecnormalize_", step, "pkl") if save_vecnormalize and vec_normalize else None,
    )
    if files.replay_buffer is not None:
        atomic_write(files.replay_buffer, model.save_replay_buffer)  # type: ignore[attr-defined]
    if files.vecnormalize is not None:
        atomic_write(files.vecnormalize, lambda path: vec_normalize.save(str(path)))  # type: ignore[union-attr]
    save_training_state(model, training_state)
    atomic_write(files.model, model.save)  # last: the checkpoint is there once its zip is
    if keep_last is not None:
        for old in find_checkpoints(root, name_prefix)[keep_last:]:
            for path in old.paths:  # the zip first: the checkpoint is gone at once
                path.unlink(missing_ok=True)
    return files


def load_checkpoint(
    checkpoint: CheckpointFiles, env: GymEnv | None, algo_class: type[BaseAlgorithm] | None = None, **load_kwargs: Any
) -> BaseAlgorithm:
    """
    Load a checkpoint: the model, its replay buffer, the random generators and the environment's state; continue with
    ``learn(remaining, reset_num_timesteps=False)``. From SB3's ``CheckpointCallback`` (no training state) the
    environment is reset and the generators reseeded, as SB3's ``load`` does (a faithful continuation).

    :param checkpoint: from :func:`latest_checkpoint` (or built with the paths of its files)
    :param env: an environment built as the saved one (its state is overwritten with the saved state)
    :param algo_class: the model's class (default: SOUP)
    :param load_kwargs: passed to ``algo_class.load`` (``device``, ``custom_objects``...)
    :return: the model
    """
    if algo_class is None:
        from sb3_soup.soup import SOUP  # sb3_soup.soup imports this module

        algo_class = SOUP
    if checkpoint.vecnormalize is not None and isinstance(env, VecEnv) and unwrap_vec_normalize(env) is None:
        env = VecNormalize.load(str(checkpoint.vecnormalize), env)
    path = checkpoint.training_state
    state = read_training_state(path) if path is not None else None
    exact = state is not None and state["env"] is not None and env is not None
    model = algo_class.load(checkpoint.model, env=env, force_reset=not exact, **load_kwargs)
    if checkpoint.replay_buffer is not None and isinstance(model, OffPolicyAlgorithm):
        # An exact resume continues the saved episodes: a HerReplayBuffer keeps its last trajectory open
        model.load_replay_buffer(checkpoint.replay_buffer, truncate_last_traj=not exact)
    if state is not None:
        restore_training_state(model, state, path)
    return model


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
