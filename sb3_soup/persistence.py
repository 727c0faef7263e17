"""
The pieces a saved run is made of, each in one place: files written atomically, the random generators' state and the
environment's state. ``SOUP.save``/``SOUP.load``, the resumable checkpoints (:mod:`sb3_soup.checkpoint`) and the
experiment runner are built on them.

- **Atomic files.** :func:`atomic_write` writes to a hidden temporary file next to the target, fsyncs it and renames
  it into place: a reader (or a process resuming after a kill) finds the whole file or the previous one, never a part.
- **Random generators.** :func:`capture_rng_state` / :func:`restore_rng_state`: Python's ``random``, NumPy's global
  generator, torch's (CPU and, when in use, CUDA) generators and an action space's generator (SB3 samples warm-up
  actions from it).
- **Environment state.** :func:`get_env_state` / :func:`set_env_state`: every attribute of every layer of a
  ``DummyVecEnv`` (VecEnv wrappers such as ``VecNormalize``, then each sub-environment's wrappers down to the
  simulator, e.g. ``Monitor``'s running episode, ``TimeLimit``'s step count, MuJoCo's ``MjData``, the env's
  ``np_random``), without the open log files.
"""

import copy
import io
import os
import pickle
import random
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cloudpickle
import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.monitor import ResultsWriter
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecEnvWrapper

TMP_MARK = ".tmp-"
"""In the names of :func:`atomic_write`'s temporary files: ``.{name}.tmp-{pid}``, next to the file being written."""

# Live objects that stay with the running environment (open log files): never saved, never replaced
_KEPT_LIVE: tuple[type, ...] = (ResultsWriter, io.IOBase)


# ---------------------------------------------------------------- atomic files


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


# ---------------------------------------------------------------- random generators


def capture_rng_state(action_space: Any = None) -> dict[str, Any]:
    """
    The states of the random generators a training run draws from.

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
    if action_space is not None and "action_space" in state and state["action_space"] is not None:
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
