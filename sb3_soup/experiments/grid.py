"""The experiment grid: model variants, suites, hyper-parameters and the (model, seed) runs they expand to."""

from __future__ import annotations

import ast
import dataclasses
import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import yaml

# Keys of an RL-Zoo hyper-parameter entry that are not algorithm constructor arguments.
ZOO_ONLY_KEYS = frozenset(
    {
        "n_timesteps",
        "policy",
        "normalize",
        "normalize_kwargs",
        "n_envs",
        "env_wrapper",
        "vec_env_wrapper",
        "frame_stack",
        "callback",
        "noise_type",
        "monitor_kwargs",
        "env_kwargs",
        "eval_env_kwargs",
    }
)

# SOUP's constructor defaults for the arguments the TD3/DDPG peers share (from API_CONTRACT.md; the paper's values).
# Used when SOUP itself cannot be imported, and to give the SB3 peers the same values as SOUP.
SOUP_SHARED_DEFAULTS: dict[str, Any] = {
    "learning_rate": 1e-4,
    "critic_learning_rate": 3e-4,
    "buffer_size": 1_000_000,
    "learning_starts": 1000,
    "batch_size": 1024,
    "tau": 1e-3,
    "gamma": 0.99,
    "train_freq": 1,
    "gradient_steps": 1,
    "noise_std": 0.2,
}

# Keys the SB3 peers (TD3, SB3's DDPG) take from the SOUP hyper-parameters; everything else is SOUP-only.
PEER_KEYS = ("learning_rate", "buffer_size", "learning_starts", "batch_size", "tau", "gamma", "train_freq", "gradient_steps")
PEER_NET_ARCH = [256, 256]
DEFAULT_HEADS = 5
HYPERPARAMS_FILE = Path(__file__).resolve().parent.parent / "hyperparams" / "soup.yml"


@dataclasses.dataclass(frozen=True)
class Variant:
    """
    One column of the paper's tables: an algorithm with fixed settings.

    :param name: the variant's name on the command line (``--models``)
    :param algo: which class trains it: ``"soup"``, ``"td3"`` (SB3's TD3) or ``"sb3_ddpg"`` (SB3's DDPG)
    :param label: the column title (``{K}`` is replaced by the number of heads)
    :param settings: constructor arguments that define the variant (``{K}`` values are replaced by the number of heads)
    :param uses_heads: whether the variant has K heads (its runs are then named ``name-k{K}``)
    """

    name: str
    algo: str
    label: str
    settings: dict[str, Any]
    uses_heads: bool = True


VARIANTS: dict[str, Variant] = {
    variant.name: variant
    for variant in (
        Variant("ddpg", "soup", "DDPG", {"preset": "ddpg"}, uses_heads=False),
        Variant("ma_bddpg", "soup", "MA-BDDPG (K={K})", {"preset": "ma_bddpg"}),
        Variant("multi_ddpg", "soup", "Multi-DDPG (K={K})", {"preset": "multi_ddpg"}),
        Variant("dbddpg", "soup", "DBDDPG (K={K})", {"preset": "dbddpg"}),
        Variant("soup", "soup", "SOUP (K={K})", {"preset": "soup"}),
        Variant("td3", "td3", "TD3", {}, uses_heads=False),
        # Not in any suite: SB3's own DDPG, a sanity baseline for the paper-faithful `ddpg` preset.
        Variant("sb3_ddpg", "sb3_ddpg", "DDPG (SB3)", {}, uses_heads=False),
        # The confidence suite: DBDDPG with each confidence strategy ("adaptive" is SOUP).
        Variant("none", "soup", "No confidence (K={K})", {"preset": "dbddpg", "confidence": "none"}),
        Variant("fixed", "soup", "Fixed confidence (K={K})", {"preset": "dbddpg", "confidence": "fixed"}),
        Variant("decayed", "soup", "Decayed confidence (K={K})", {"preset": "dbddpg", "confidence": "decayed"}),
        Variant("adaptive", "soup", "Self-adaptive confidence (K={K})", {"preset": "dbddpg", "confidence": "adaptive"}),
    )
}

# suite name -> (variant names in table order, default head counts)
SUITES: dict[str, tuple[tuple[str, ...], tuple[int, ...]]] = {
    "models": (("ddpg", "ma_bddpg", "multi_ddpg", "dbddpg", "soup", "td3"), (DEFAULT_HEADS,)),
    "confidence": (("none", "fixed", "decayed", "adaptive"), (DEFAULT_HEADS,)),
    "heads": (("soup",), (3, 5, 10)),
}


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """
    Everything one worker needs to train (or resume) one (model, seed) run. JSON-serialisable.

    :param env_id: Gymnasium environment id
    :param model: the run's model id, e.g. ``"soup-k5"`` or ``"td3"``
    :param variant: the variant's name (a key of :data:`VARIANTS`)
    :param algo: ``"soup"``, ``"td3"`` or ``"sb3_ddpg"``
    :param label: the model's column title
    :param n_heads: the number of heads K (``None`` for single-head models)
    :param seed: the random seed
    :param timesteps: total environment steps of the run
    :param hyperparams: algorithm constructor arguments (``policy_kwargs`` may be a Python expression string)
    :param run_dir: the run's folder
    :param checkpoint_freq: save a checkpoint every this many steps
    :param stop_after: stop (resumably) after this many new steps in this session; ``None``: run to the end
    """

    env_id: str
    model: str
    variant: str
    algo: str
    label: str
    n_heads: int | None
    seed: int
    timesteps: int
    hyperparams: dict[str, Any]
    run_dir: str
    checkpoint_freq: int = 10_000
    stop_after: int | None = None

    @property
    def key(self) -> str:
        """The run's name: ``model/seed_N``."""
        return f"{self.model}/seed_{self.seed}"

    def config(self) -> dict[str, Any]:
        """The settings that define the run's results (what must match to resume it)."""
        data = dataclasses.asdict(self)
        for volatile in ("run_dir", "checkpoint_freq", "stop_after"):
            data.pop(volatile)
        return data

    def to_json(self) -> str:
        """:return: the spec as JSON"""
        return json.dumps(dataclasses.asdict(self), indent=2, sort_keys=True)


def soup_defaults() -> dict[str, Any]:
    """
    :return: SOUP's constructor defaults for the keys in :data:`SOUP_SHARED_DEFAULTS`, read from the class when
        it is importable, else the contract's values.
    """
    try:
        import inspect

        from sb3_soup import SOUP  # type: ignore[attr-defined]
    except ImportError:
        return dict(SOUP_SHARED_DEFAULTS)
    signature = inspect.signature(SOUP.__init__)
    defaults = dict(SOUP_SHARED_DEFAULTS)
    for key in defaults:
        parameter = signature.parameters.get(key)
        if parameter is not None and parameter.default is not inspect.Parameter.empty:
            defaults[key] = parameter.default
    return defaults


def fallback_hyperparams(env_id: str) -> dict[str, Any]:
    """
    Hyper-parameters for an environment that ``soup.yml`` does not list: SOUP's defaults (the paper's values),
    with a smaller buffer and batch for the classic-control tasks so that they stay cheap.

    :param env_id: the environment id
    :return: the constructor arguments
    """
    params: dict[str, Any] = {}
    if not any(env_id.startswith(prefix) for prefix in ("Hopper", "Walker2d", "HalfCheetah", "Ant", "Humanoid", "Swimmer")):
        params.update(batch_size=256, buffer_size=200_000)
    return params


def load_hyperparams(env_id: str, path: str | os.PathLike | None = None) -> dict[str, Any]:
    """
    The SOUP hyper-parameters of an environment from an RL-Zoo style file, without the zoo-only keys.

    :param env_id: the environment id (a top-level key of the file)
    :param path: the YAML file; default: ``sb3_soup/hyperparams/soup.yml``
    :return: constructor arguments (``policy_kwargs`` left as the file gives it); the fallback when the file or
        the environment's entry is missing
    """
    file = Path(path) if path is not None else HYPERPARAMS_FILE
    if not file.is_file():
        if path is not None:
            raise FileNotFoundError(f"Hyper-parameter file not found: {file}")
        return fallback_hyperparams(env_id)
    with open(file) as stream:
        entries = yaml.safe_load(stream) or {}
    if env_id not in entries:
        return fallback_hyperparams(env_id)
    return {key: value for key, value in dict(entries[env_id]).items() if key not in ZOO_ONLY_KEYS}


def parse_overrides(items: Iterable[str]) -> dict[str, dict[str, Any]]:
    """
    Parse ``--hyperparams`` items: ``key=value`` applies to every model, ``model:key=value`` to one variant
    (or one model id such as ``soup-k10``). Values are Python literals where they parse as one, else strings.

    :param items: the items
    :return: ``{"*" or model: {key: value}}``
    """
    overrides: dict[str, dict[str, Any]] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"Expected key=value or model:key=value, got {item!r}")
        target_key, raw = item.split("=", 1)
        target, key = target_key.split(":", 1) if ":" in target_key else ("*", target_key)
        try:
            value: Any = ast.literal_eval(raw)
        except (ValueError, SyntaxError):
            value = raw
        overrides.setdefault(target, {})[key.strip()] = value
    return overrides


def parse_seeds(text: str) -> list[int]:
    """
    :param text: a count (``"3"`` -> seeds 0, 1, 2) or a comma-separated list (``"1,5"``)
    :return: the seeds
    """
    if "," in text:
        return [int(part) for part in text.split(",") if part.strip()]
    return list(range(int(text)))


def _format(value: Any, n_heads: int | None) -> Any:
    return value.replace("{K}", str(n_heads)) if isinstance(value, str) else value


def peer_hyperparams(params: dict[str, Any]) -> dict[str, Any]:
    """
    Map SOUP hyper-parameters onto SB3's TD3/DDPG: the shared keys, net_arch [256, 256], and the Gaussian
    exploration noise's std as ``noise_std`` (turned into ``NormalActionNoise`` by the runner).

    :param params: resolved SOUP hyper-parameters
    :return: the peer's hyper-parameters
    """
    peer = {key: params[key] for key in PEER_KEYS if key in params}
    peer["policy_kwargs"] = {"net_arch": list(PEER_NET_ARCH)}
    peer["noise_std"] = params.get("noise_std", SOUP_SHARED_DEFAULTS["noise_std"])
    return peer


def build_grid(
    env_id: str,
    out: str | os.PathLike,
    suite: str = "models",
    models: Sequence[str] | None = None,
    heads: Sequence[int] | None = None,
    seeds: Sequence[int] = (0, 1, 2),
    timesteps: int | None = None,
    overrides: dict[str, dict[str, Any]] | None = None,
    hyperparams_file: str | os.PathLike | None = None,
    checkpoint_freq: int = 10_000,
    stop_after: int | None = None,
) -> list[RunSpec]:
    """
    Expand a suite into its runs.

    Precedence of hyper-parameters, lowest first: SOUP's defaults, the env's ``soup.yml`` entry (or the fallback),
    the variant's own settings (preset, confidence, K), the ``*`` overrides, the variant's/model's overrides.

    :param env_id: the environment id
    :param out: the experiment folder (runs go to ``out/model/seed_N``)
    :param suite: ``"models"``, ``"confidence"`` or ``"heads"``
    :param models: narrow the suite to these variants (any name in :data:`VARIANTS` is accepted)
    :param heads: the head counts K (default: the suite's)
    :param seeds: the seeds
    :param timesteps: steps per run (default: the yml's ``n_timesteps``, else 100k)
    :param overrides: from :func:`parse_overrides`
    :param hyperparams_file: the RL-Zoo style file to read
    :param checkpoint_freq: checkpoint every this many steps
    :param stop_after: see :class:`RunSpec`
    :return: the runs, in table order (model, then seed)
    """
    if suite not in SUITES:
        raise ValueError(f"Unknown suite {suite!r}; choose from {sorted(SUITES)}")
    suite_models, suite_heads = SUITES[suite]
    names = list(models) if models else list(suite_models)
    unknown = [name for name in names if name not in VARIANTS]
    if unknown:
        raise ValueError(f"Unknown model(s) {unknown}; choose from {sorted(VARIANTS)}")
    head_counts = list(heads) if heads else list(suite_heads)
    overrides = overrides or {}
    base = {**soup_defaults(), **load_hyperparams(env_id, hyperparams_file)}
    if timesteps is None:
        timesteps = int(_zoo_timesteps(env_id, hyperparams_file) or 100_000)
    specs = []
    for name in names:
        variant = VARIANTS[name]
        for n_heads in head_counts if variant.uses_heads else [None]:
            model = f"{name}-k{n_heads}" if n_heads is not None else name
            params = dict(base)
            params.update({key: _format(value, n_heads) for key, value in variant.settings.items()})
            if n_heads is not None:
                params["n_heads"] = n_heads
            params.update(overrides.get("*", {}))
            params.update(overrides.get(name, {}))
            params.update(overrides.get(model, {}))
            if variant.algo != "soup":
                params = {**peer_hyperparams(params), **overrides.get(name, {}), **overrides.get(model, {})}
            for seed in seeds:
                specs.append(
                    RunSpec(
                        env_id=env_id,
                        model=model,
                        variant=name,
                        algo=variant.algo,
                        label=variant.label.replace("{K}", str(n_heads)),
                        n_heads=n_heads,
                        seed=int(seed),
                        timesteps=int(timesteps),
                        hyperparams=params,
                        run_dir=str(Path(out) / model / f"seed_{seed}"),
                        checkpoint_freq=int(checkpoint_freq),
                        stop_after=stop_after,
                    )
                )
    return specs


def _zoo_timesteps(env_id: str, path: str | os.PathLike | None) -> float | None:
    file = Path(path) if path is not None else HYPERPARAMS_FILE
    if not file.is_file():
        return None
    with open(file) as stream:
        entry = (yaml.safe_load(stream) or {}).get(env_id) or {}
    value = entry.get("n_timesteps")
    return float(value) if value is not None else None
