"""The experiment grid: model variants, suites, hyper-parameters and the (model, seed) runs they expand to."""

from __future__ import annotations

import ast
import dataclasses
import importlib.util
import json
import os
import re
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

# Keys the SB3 peers (TD3, SB3's DDPG) take from the SOUP hyper-parameters; everything else is SOUP-only.
PEER_KEYS = ("learning_rate", "buffer_size", "learning_starts", "batch_size", "tau", "gamma", "train_freq", "gradient_steps")
PEER_NET_ARCH = [256, 256]
DEFAULT_HEADS = 5
# Where a variant's hyper-parameters come from (see Variant.source) and, for SOUP's, the RL-Zoo file of each
SOURCES = ("paper", "defaults", "zoo")
SOURCE_FILES = {"paper": "soup_paper", "defaults": "soup"}


@dataclasses.dataclass(frozen=True)
class Variant:
    """
    One column of the paper's tables: an algorithm with fixed settings.

    :param name: the variant's name on the command line (``--models``)
    :param algo: which class trains it: ``"soup"``, ``"td3"`` (SB3's TD3) or ``"sb3_ddpg"`` (SB3's DDPG)
    :param label: the column title (``{K}`` is replaced by the number of heads)
    :param settings: constructor arguments that define the variant (``{K}`` values are replaced by the number of heads)
    :param uses_heads: whether the variant has K heads (its runs are then named ``name-k{K}``)
    :param same_as: another variant that trains exactly the same model (e.g. the confidence suite's ``none`` is the
        models suite's ``dbddpg``): its runs are shared, stored under that variant's name, as long as no
        ``--hyperparams`` override tells them apart
    :param source: where its hyper-parameters come from: ``"paper"``, the paper's
        (:func:`sb3_soup.presets.paper_hyperparams` and ``hyperparams/soup_paper.yml``'s entry for the env; the SB3
        peers take the keys they share with SOUP, see :func:`peer_hyperparams`); ``"defaults"``, SOUP's defaults (its
        constructor's, and ``hyperparams/soup.yml``'s entry, what ``rl_zoo3.train --algo soup`` uses); or ``"zoo"``, the
        RL Zoo's own entry for the algorithm and the env (``rl_zoo3/hyperparams/td3.yml``, ``ddpg.yml``), as the Zoo
        trains it
    """

    name: str
    algo: str
    label: str
    settings: dict[str, Any]
    uses_heads: bool = True
    same_as: str | None = None
    source: str = "paper"


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
        # The benchmark suite's peers: SB3's DDPG and TD3 exactly as the RL Zoo trains them (its MuJoCo entries: lr 1e-3,
        # batch 256, tau 0.005, N(0, 0.1) noise, 10k random steps, net_arch [400, 300]).
        Variant("ddpg_zoo", "sb3_ddpg", "DDPG (RL Zoo)", {}, uses_heads=False, source="zoo"),
        Variant("td3_zoo", "td3", "TD3 (RL Zoo)", {}, uses_heads=False, source="zoo"),
        Variant("sac_zoo", "sac", "SAC (RL Zoo)", {}, uses_heads=False, source="zoo"),
        # The benchmark suite's SOUPs: with its defaults (what a user gets), and the paper's (the models suite's soup)
        Variant("soup_defaults", "soup", "SOUP (defaults)", {}, uses_heads=False, source="defaults"),
        Variant("soup_paper", "soup", "SOUP, the paper's (K={K})", {"preset": "soup"}, same_as="soup"),
        # The confidence suite: DBDDPG (K actor and K critic heads, bootstrap masks) with each confidence strategy.
        # "none" is the dbddpg preset and "adaptive" the soup preset, so they share the models suite's runs. A preset
        # fixes the confidence, so "fixed" and "decayed" are given without one: SOUP's defaults are then K x K heads
        # with masks, which is what the dbddpg preset sets too.
        Variant("none", "soup", "No confidence (K={K})", {"preset": "dbddpg"}, same_as="dbddpg"),
        Variant("fixed", "soup", "Fixed confidence (K={K})", {"confidence": "fixed"}),
        Variant("decayed", "soup", "Decayed confidence (K={K})", {"confidence": "decayed"}),
        Variant("adaptive", "soup", "Self-adaptive confidence (K={K})", {"preset": "soup"}, same_as="soup"),
    )
}


DEFAULT_SEEDS = 3  # seeds per variant of a suite, unless the suite or the command gives others


@dataclasses.dataclass(frozen=True)
class Suite:
    """
    One of the paper's comparisons.

    :param variants: its variants, in table order
    :param heads: its default head counts K
    :param baseline: the variant Speed Up is measured against by default (Table 1: DDPG)
    :param seeds: how many seeds (0, 1, ...) a run of the suite gives each variant when no seeds are given; the
        variants it leaves out get :data:`DEFAULT_SEEDS`
    """

    variants: tuple[str, ...]
    heads: tuple[int, ...]
    baseline: str
    seeds: dict[str, int] = dataclasses.field(default_factory=dict)

    def seeds_of(self, variant: str) -> list[int]:
        """:return: the seeds a run of the suite gives ``variant`` by default"""
        return list(range(self.seeds.get(variant, DEFAULT_SEEDS)))


SUITES: dict[str, Suite] = {
    # Table 1 and Figure 4.
    "models": Suite(("ddpg", "ma_bddpg", "multi_ddpg", "dbddpg", "soup", "td3"), (DEFAULT_HEADS,), "ddpg"),
    # Figure 5 and 6. No DDPG column: Speed Up is against DBDDPG without confidence, what the strategies are added to.
    "confidence": Suite(("none", "fixed", "decayed", "adaptive"), (DEFAULT_HEADS,), "none"),
    # Figure 7 (and Table 1's K=10 columns): Speed Up against DDPG when the folder has it (the models suite's runs).
    "heads": Suite(("soup",), (3, 5, 10), "ddpg"),
    # What peers publish: deterministic evaluations of SOUP against SB3's TD3, DDPG and SAC as the RL Zoo trains them,
    # SOUP's defaults and TD3 with 5 seeds, the others with 3 (issue 19)
    "benchmark": Suite(
        ("soup_defaults", "soup_paper", "ddpg_zoo", "td3_zoo", "sac_zoo"),
        (DEFAULT_HEADS,),
        "ddpg_zoo",
        seeds={"soup_defaults": 5, "td3_zoo": 5},
    ),
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
    :param eval_freq: evaluate the deterministic policy every this many steps (0: never), as SB3's ``EvalCallback``
    :param eval_episodes: episodes per evaluation
    :param net_arch: a SOUP run's networks as its ``policy_kwargs`` build them (:func:`soup_net_arch`), recorded so that
        a spec keeps its meaning when a default architecture changes; ``None`` for the SB3 algorithms, and in a SOUP
        spec written before specs recorded it (read as the networks of then, :data:`SPEC_ACTION_LAYER_BEFORE`)
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
    eval_freq: int = 10_000
    eval_episodes: int = 10
    net_arch: dict[str, Any] | None = None

    @property
    def key(self) -> str:
        """The run's name in its experiment folder (one env): ``model/seed_N``."""
        return f"{self.model}/seed_{self.seed}"

    @property
    def run_id(self) -> str:
        """The run's name in a grid of several envs (``screen run``): ``env_id/model/seed_N``."""
        return f"{self.env_id}/{self.key}"

    def config(self) -> dict[str, Any]:
        """
        The run's identity: the settings that define its results (environment, algorithm, hyper-parameters, seed,
        budget, SOUP's networks), what must match to resume, skip or share it. Names (``model``, ``variant``,
        ``label``) and where or how it runs (``run_dir``, ``checkpoint_freq``, ``stop_after``) are not part of it.

        :return: the settings, JSON-normalised (tuples as lists), so a spec read back from ``spec.json`` compares equal
        """
        data = dataclasses.asdict(self)
        for name in ("model", "variant", "label", "run_dir", "checkpoint_freq", "stop_after"):
            data.pop(name)
        if self.algo == "soup" and self.net_arch is None:  # a spec from before specs recorded the networks
            data["net_arch"] = soup_net_arch(self.hyperparams, default_action_layer=SPEC_ACTION_LAYER_BEFORE)
        return json.loads(json.dumps(data))

    def to_json(self) -> str:
        """:return: the spec as JSON"""
        return json.dumps(dataclasses.asdict(self), indent=2, sort_keys=True)


SPEC_ACTION_LAYER_BEFORE = 1
"""Where the action joined the critic in a SOUP run whose ``spec.json`` has no ``net_arch`` (written before specs
recorded the networks, when the default was the paper's critic) and whose ``policy_kwargs`` leave it to the default."""


def soup_net_arch(hyperparams: dict[str, Any], default_action_layer: int | None = None) -> dict[str, Any]:
    """
    The networks a SOUP run builds, every key set (:func:`sb3_soup.policies.parse_net_arch` of the ``net_arch`` in its
    ``policy_kwargs``, a dict or an RL-Zoo style string).

    :param hyperparams: the run's constructor arguments
    :param default_action_layer: where the action joins the critic when ``net_arch`` is SOUP's form and does not say;
        ``None``: SOUP's default today
    :return: SOUP's form of ``net_arch``
    """
    from sb3_soup.experiments.runner import resolve_policy_kwargs
    from sb3_soup.policies import parse_net_arch

    net_arch = (resolve_policy_kwargs(hyperparams.get("policy_kwargs")) or {}).get("net_arch")
    return parse_net_arch(net_arch, default_action_layer)


def soup_defaults() -> dict[str, Any]:
    """
    :return: SOUP's constructor defaults that define a run (not those of logging and devices), ``None``s left out,
        so that a run's ``spec.json`` records every setting it trained with
    """
    import inspect

    from sb3_soup import SOUP

    ignored = {"self", "policy", "env", "device", "verbose", "tensorboard_log", "seed", "_init_setup_model", "check_finite"}
    return {
        name: parameter.default
        for name, parameter in inspect.signature(SOUP.__init__).parameters.items()
        if name not in ignored and parameter.default is not inspect.Parameter.empty and parameter.default is not None
    }


def fallback_hyperparams(env_id: str, source: str) -> dict[str, Any]:
    """
    Hyper-parameters for an environment that the source's file does not list: none for SOUP's defaults; for the
    paper's (sized for MuJoCo), a smaller buffer and batch on the classic-control tasks so that they stay cheap.

    :param env_id: the environment id
    :param source: ``"paper"`` or ``"defaults"``
    :return: the constructor arguments
    """
    mujoco = any(env_id.startswith(prefix) for prefix in ("Hopper", "Walker2d", "HalfCheetah", "Ant", "Humanoid", "Swimmer"))
    return {} if source == "defaults" or mujoco else dict(batch_size=256, buffer_size=200_000)


def hyperparams_file(source: str, path: str | os.PathLike | None = None) -> Path:
    """
    :param source: ``"paper"`` or ``"defaults"``
    :param path: the user's file (``--hyperparams-file``), which replaces the source's own
    :return: the RL-Zoo file SOUP's hyper-parameters of that source are read from
    """
    from sb3_soup.presets import hyperparams_file as installed_file

    return Path(path) if path is not None else installed_file(SOURCE_FILES[source])


def load_hyperparams(env_id: str, path: str | os.PathLike | None = None, source: str = "paper") -> dict[str, Any]:
    """
    The SOUP hyper-parameters of an environment from an RL-Zoo style file, without the zoo-only keys.

    :param env_id: the environment id (a top-level key of the file)
    :param path: the YAML file; default: the source's (``hyperparams/soup_paper.yml`` or ``hyperparams/soup.yml``)
    :param source: ``"paper"`` or ``"defaults"``
    :return: constructor arguments (``policy_kwargs`` left as the file gives it); the fallback when the env has no entry
    """
    file = hyperparams_file(source, path)
    if not file.is_file():
        raise FileNotFoundError(f"Hyper-parameter file not found: {file}")
    with open(file) as stream:
        entries = yaml.safe_load(stream) or {}
    if env_id not in entries:
        return fallback_hyperparams(env_id, source)
    entry = dict(entries[env_id])
    # SOUP's decaying noise is SOUP's argument (the runner builds it): its noise_type stays
    from sb3_soup.noise import is_decaying_normal

    keep = {"noise_type"} if is_decaying_normal(entry) else set()
    return {key: value for key, value in entry.items() if key not in ZOO_ONLY_KEYS - keep}


def base_hyperparams(source: str, env_id: str, path: str | os.PathLike | None = None) -> dict[str, Any]:
    """
    :param source: ``"paper"`` or ``"defaults"`` (see :attr:`Variant.source`)
    :param env_id: the environment id
    :param path: the user's hyper-parameter file, if any
    :return: SOUP's constructor arguments for the env before a variant's own settings
    """
    from sb3_soup.presets import paper_hyperparams

    base = paper_hyperparams() if source == "paper" else soup_defaults()
    return {**base, **load_hyperparams(env_id, path, source)}


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


def read_candidates(path: str | os.PathLike, only: Sequence[str] | None = None) -> dict[str, dict[str, Any]]:
    """
    SOUP's candidates for a screen, from a YAML file mapping each candidate's name (its runs' folder) to its settings
    (SOUP's defaults with these; the RL Zoo's forms, e.g. ``policy_kwargs: "dict(layer_norm=True)"``), in the file's order.

    :param path: the file (e.g. ``docs/results/screen/candidates.yml``)
    :param only: these candidates only, in this order
    :return: ``{name: settings}``
    """
    import yaml

    data = yaml.safe_load(Path(path).read_text())
    if not isinstance(data, dict) or not all(isinstance(value, dict) for value in data.values()):
        raise ValueError(f"{path} must map each candidate's name to a mapping of its settings, got {data!r}")
    for name in data:
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_.+-]+", name) or name in VARIANTS:
            raise ValueError(
                f"{path}: candidate names are folder names (letters, digits, _.+-) other than the variants' "
                f"({', '.join(VARIANTS)}), got {name!r}"
            )
    unknown = [name for name in only or [] if name not in data]
    if unknown:
        raise ValueError(f"{path} has no candidates {unknown}; it has {list(data)}")
    return {name: dict(data[name]) for name in (only or data)}


def parse_seeds(text: str) -> list[int]:
    """
    :param text: a count (``"3"`` -> seeds 0, 1, 2) or a comma-separated list (``"1,5"``; one seed: ``"0,"``)
    :return: the seeds
    :raises ValueError: for a count below 1, an empty list, a negative or repeated seed, or text of neither form
    """
    accepted = (
        "a count of at least 1 (3 -> seeds 0, 1, 2) or a comma-separated list of distinct seeds >= 0 "
        "(1,5; for seed 0 alone write 0,)"
    )
    try:
        seeds = [int(part) for part in text.split(",") if part.strip()] if "," in text else list(range(int(text)))
    except ValueError:
        seeds = []
    if not seeds or min(seeds) < 0 or len(set(seeds)) < len(seeds):
        raise ValueError(f"seeds={text!r}: expected {accepted}")
    return seeds


def _format(value: Any, n_heads: int | None) -> Any:
    return value.replace("{K}", str(n_heads)) if isinstance(value, str) else value


def peer_hyperparams(params: dict[str, Any]) -> dict[str, Any]:
    """
    Map SOUP hyper-parameters onto SB3's TD3/DDPG: the shared keys, net_arch [256, 256], and the Gaussian
    exploration noise's initial std as ``noise_std`` (a constant ``NormalActionNoise``, built by the runner; SOUP's
    default, 0.1, when SOUP's settings have none).

    :param params: resolved SOUP hyper-parameters
    :return: the peer's hyper-parameters
    """
    from sb3_soup.noise import DEFAULT_NOISE_STD

    peer = {key: params[key] for key in PEER_KEYS if key in params}
    peer["policy_kwargs"] = {"net_arch": list(PEER_NET_ARCH)}
    peer["noise_std"] = params.get("noise_std", DEFAULT_NOISE_STD)
    return peer


def build_grid(
    env_id: str,
    out: str | os.PathLike,
    suite: str = "models",
    models: Sequence[str] | None = None,
    heads: Sequence[int] | None = None,
    seeds: Sequence[int] | None = None,
    timesteps: int | None = None,
    overrides: dict[str, dict[str, Any]] | None = None,
    hyperparams_file: str | os.PathLike | None = None,
    checkpoint_freq: int = 10_000,
    stop_after: int | None = None,
    eval_freq: int = 10_000,
    eval_episodes: int = 10,
    name: str | None = None,
) -> list[RunSpec]:
    """
    Expand a suite into its runs.

    Precedence of hyper-parameters, lowest first: the variant's source (the paper's settings or SOUP's defaults, then the
    env's entry in the source's file, or the fallback), the variant's own settings (preset, confidence, K), the ``*``
    overrides, the variant's/model's overrides. The RL Zoo's peers (``source="zoo"``) take their own entry and the
    overrides aimed at them by name only.
    A variant that is :attr:`Variant.same_as` another (``none`` = ``dbddpg``, ``adaptive`` = ``soup``) is stored as
    that one (same folder, name and label), so that suites run into one folder share the run instead of training it
    twice; overrides aimed at it by name make it a run of its own (``none-k5``).

    :param env_id: the environment id
    :param out: the experiment folder (runs go to ``out/model/seed_N``)
    :param suite: ``"models"``, ``"confidence"`` or ``"heads"``
    :param models: narrow the suite to these variants (any name in :data:`VARIANTS` is accepted)
    :param heads: the head counts K (default: the suite's)
    :param seeds: the seeds of every model (default: the suite's, :meth:`Suite.seeds_of`)
    :param timesteps: steps per run (default: the ``n_timesteps`` of the env's entry in the variants' files, else 100k)
    :param overrides: from :func:`parse_overrides`
    :param hyperparams_file: an RL-Zoo style file to read instead of the variants' own (see :attr:`Variant.source`)
    :param checkpoint_freq: checkpoint every this many steps
    :param stop_after: see :class:`RunSpec`
    :param eval_freq: see :class:`RunSpec`
    :param eval_episodes: see :class:`RunSpec`
    :param name: store the runs as this model (its folder name and column title) instead of the variant's id: for
        ablations, several settings of one variant (``--hyperparams``) side by side in one folder; needs exactly one
        model and one K
    :return: the runs, in table order (model, then seed)
    """
    if suite not in SUITES:
        raise ValueError(f"Unknown suite {suite!r}; choose from {sorted(SUITES)}")
    names = list(models) if models else list(SUITES[suite].variants)
    unknown = [variant_name for variant_name in names if variant_name not in VARIANTS]
    if unknown:
        raise ValueError(f"Unknown model(s) {unknown}; choose from {sorted(VARIANTS)}")
    head_counts = list(heads) if heads else list(SUITES[suite].heads)
    if name is not None and (len(names) != 1 or (VARIANTS[names[0]].uses_heads and len(head_counts) != 1)):
        raise ValueError(f"a name ({name!r}) stands for one model: give exactly one of --models and at most one of --heads")
    if name is not None and not re.fullmatch(r"[A-Za-z0-9_.+-]+", name):
        raise ValueError(f"a name is a folder name: letters, digits and _ . + - only, got {name!r}")
    overrides = overrides or {}
    sources = {VARIANTS[variant_name].source for variant_name in names} - {"zoo"}
    bases = {source: base_hyperparams(source, env_id, hyperparams_file) for source in sources}
    if timesteps is None:
        budgets = [_zoo_timesteps(env_id, hyperparams_file, source) for source in sorted(sources)]
        timesteps = int(max([budget for budget in budgets if budget is not None], default=100_000))
    specs = []
    for variant_name in names:
        variant = VARIANTS[variant_name]
        for n_heads in head_counts if variant.uses_heads else [None]:
            params = variant_params(variant, env_id, n_heads, bases, overrides)
            # stored as its twin (same_as) when their settings agree
            twin = None if variant.same_as is None else VARIANTS[variant.same_as]
            same = twin is not None and variant_params(twin, env_id, n_heads, bases, overrides) == params
            stored = twin if same and twin is not None else variant
            model = name or _model_id(stored.name, n_heads)
            label = name or _format(stored.label, n_heads)
            for seed in SUITES[suite].seeds_of(variant_name) if seeds is None else seeds:
                specs.append(
                    RunSpec(
                        env_id=env_id,
                        model=model,
                        variant=stored.name,
                        algo=stored.algo,
                        label=label,
                        n_heads=n_heads,
                        seed=int(seed),
                        timesteps=int(timesteps),
                        hyperparams=params,
                        run_dir=str(Path(out) / model / f"seed_{seed}"),
                        checkpoint_freq=int(checkpoint_freq),
                        stop_after=stop_after,
                        eval_freq=int(eval_freq),
                        eval_episodes=int(eval_episodes),
                        net_arch=soup_net_arch(params) if stored.algo == "soup" else None,
                    )
                )
    return specs


def _model_id(name: str, n_heads: int | None) -> str:
    return f"{name}-k{n_heads}" if n_heads is not None else name


ZOO_NOISE_TYPE = "normal"


def zoo_hyperparams(algo: str, env_id: str) -> dict[str, Any]:
    """
    The RL Zoo's own hyper-parameters for an SB3 algorithm on an env, as ``python -m rl_zoo3.train`` reads them: the
    env's entry, or the file's ``default`` entry for an env it does not list (what the Zoo itself falls back to).

    :param algo: ``"td3"``, ``"sb3_ddpg"`` or ``"sac"``
    :param env_id: the environment id
    :return: constructor arguments, with the Gaussian noise's std as ``noise_std`` where the entry sets a noise type
        (the runner makes it ``NormalActionNoise``; TD3 and DDPG without one get ``noise_std`` 0)
    """
    # Found, not imported: importing rl_zoo3 replaces gymnasium's TimeLimit for the whole process (rl_zoo3.gym_patches),
    # and an env made afterwards no longer matches the state of one made before (sb3_soup.checkpoint.set_env_state)
    package = importlib.util.find_spec("rl_zoo3")
    if package is None or package.origin is None:
        raise ImportError("the RL Zoo's hyper-parameters need rl_zoo3: pip install rl-zoo3")
    zoo_algo = {"td3": "td3", "sb3_ddpg": "ddpg", "sac": "sac"}[algo]
    file = Path(package.origin).parent / "hyperparams" / f"{zoo_algo}.yml"
    with open(file) as stream:
        entries = yaml.safe_load(stream) or {}
    name = env_id if env_id in entries else "default"
    if name not in entries:
        raise ValueError(f"the RL Zoo has no {zoo_algo} hyper-parameters for {env_id} nor a default entry (in {file})")
    entry = dict(entries[name])
    noise_type = entry.get("noise_type")
    if noise_type not in (None, ZOO_NOISE_TYPE):
        raise ValueError(f"the RL Zoo's {zoo_algo} entry for {env_id} uses {noise_type!r} noise; the runner supports 'normal'")
    params = {key: value for key, value in entry.items() if key not in ZOO_ONLY_KEYS}
    if noise_type or algo != "sac":
        params["noise_std"] = float(entry.get("noise_std", 0.0)) if noise_type else 0.0
    return params


def variant_params(
    variant: Variant,
    env_id: str,
    n_heads: int | None,
    bases: dict[str, dict[str, Any]],
    overrides: dict[str, dict[str, Any]],
) -> dict[str, Any]:
    """
    A variant's constructor arguments.

    :param variant: the variant
    :param env_id: the environment id
    :param n_heads: its K (``None`` for single-head variants)
    :param bases: source -> SOUP's hyper-parameters for the env (:func:`base_hyperparams`), for the SOUP-sourced variants
    :param overrides: from :func:`parse_overrides`
    :return: the resolved hyper-parameters
    """
    model = _model_id(variant.name, n_heads)
    if variant.source == "zoo":
        return {**zoo_hyperparams(variant.algo, env_id), **overrides.get(variant.name, {}), **overrides.get(model, {})}
    params = dict(bases[variant.source])
    params.update({key: _format(value, n_heads) for key, value in variant.settings.items()})
    if n_heads is not None:
        params["n_heads"] = n_heads
    params.update(overrides.get("*", {}))
    params.update(overrides.get(variant.name, {}))
    params.update(overrides.get(model, {}))
    if variant.algo != "soup":
        params = {**peer_hyperparams(params), **overrides.get(variant.name, {}), **overrides.get(model, {})}
    return params


def suite_columns(spec: RunSpec, extra_heads: dict[str, Sequence[int]] | None = None) -> dict[str, tuple[str, str]]:
    """
    The suites a run belongs to and its column in each. A run belongs to a suite when its variant is one of the
    suite's (directly, or as the variant another is :attr:`Variant.same_as`, e.g. ``dbddpg`` is the confidence suite's
    ``none``) and its K is one of the suite's head counts: the default ones, or ``extra_heads`` (those a ``run
    --heads`` asked for, as recorded in ``grid.json``).

    A run given its own name (``run --name``) keeps it as its title in every suite: it is not the variant's run.

    :param spec: the run
    :param extra_heads: suite -> head counts used beyond the suite's defaults
    :return: suite -> (the suite's variant, its column title)
    """
    named = spec.model != _model_id(spec.variant, spec.n_heads)
    columns = {}
    for suite_name, suite in SUITES.items():
        allowed = {*suite.heads, *(extra_heads or {}).get(suite_name, ())}
        if spec.n_heads is not None and spec.n_heads not in allowed:
            continue
        for name in suite.variants:
            variant = VARIANTS[name]
            if spec.variant in (variant.name, variant.same_as):
                columns[suite_name] = (name, spec.label if named else _format(variant.label, spec.n_heads))
                break
    return columns


def _zoo_timesteps(env_id: str, path: str | os.PathLike | None, source: str) -> float | None:
    file = hyperparams_file(source, path)
    if not file.is_file():
        return None
    with open(file) as stream:
        entry = (yaml.safe_load(stream) or {}).get(env_id) or {}
    value = entry.get("n_timesteps")
    return float(value) if value is not None else None


@dataclasses.dataclass(frozen=True)
class ScreenTask:
    """
    One task of the screening suite (:data:`SCREEN_TASKS`).

    :param env_id: the Gymnasium environment id (the task's experiment folder is ``ROOT/env_id``)
    :param timesteps: the budget of every run on it: a run's score is its deterministic evaluation at this step
    :param learning_starts: the random warm-up of every model on it, the baselines and SOUP's candidates alike
    """

    env_id: str
    timesteps: int
    learning_starts: int


# The screening suite (issue 19): tasks where TD3 with the RL Zoo's settings learns within a short budget (one seed of
# one model well under an hour of one core), balancing, reaching and locomotion plus classic control. Every model
# trains on a task with its budget and warm-up, is evaluated every SCREEN_EVAL_FREQ steps on SCREEN_EVAL_EPISODES
# deterministic episodes, and scores its final evaluation's mean return. The baselines' runs were started with
# `run --env ENV --suite benchmark --models MODEL --seeds 5 --timesteps BUDGET --eval-freq 5000
# --hyperparams MODEL:learning_starts=WARMUP --out ROOT/ENV`: build_screen builds exactly those runs, so it reuses them.
SCREEN_TASKS: tuple[ScreenTask, ...] = (
    ScreenTask("Pendulum-v1", 20_000, 5_000),
    ScreenTask("InvertedPendulum-v4", 20_000, 5_000),
    ScreenTask("InvertedDoublePendulum-v4", 20_000, 5_000),
    ScreenTask("Reacher-v4", 30_000, 5_000),
    ScreenTask("Swimmer-v4", 50_000, 10_000),
    ScreenTask("HalfCheetah-v4", 50_000, 10_000),
    ScreenTask("Hopper-v4", 50_000, 10_000),
    ScreenTask("Walker2d-v4", 50_000, 10_000),
)
SCREEN_EVAL_FREQ = 5_000
SCREEN_EVAL_EPISODES = 10
SCREEN_SEEDS = 5
# The peers, trained once per ROOT and reused by every later screen; the reference is normalised score 1 on each task.
SCREEN_BASELINES = ("td3_zoo", "ddpg_zoo", "sac_zoo")
SCREEN_REFERENCE = "td3_zoo"
# The suite each task's grid.json records the runs under (as the baselines' `run --suite benchmark` did).
SCREEN_SUITE = "benchmark"
# Settings a task fixes for every model: a screen cannot override them.
SCREEN_FIXED_KEYS = ("learning_starts",)


def screen_tasks(env_ids: Sequence[str] | None = None) -> list[ScreenTask]:
    """
    :param env_ids: narrow the suite to these tasks (``None``: all of :data:`SCREEN_TASKS`, in its order)
    :return: the tasks, in the order given
    """
    known = {task.env_id: task for task in SCREEN_TASKS}
    if env_ids is None:
        return list(SCREEN_TASKS)
    unknown = [env_id for env_id in env_ids if env_id not in known]
    if unknown:
        raise ValueError(f"Unknown screen task(s) {unknown}; the suite has {list(known)}")
    return [known[env_id] for env_id in env_ids]


def build_screen(
    root: str | os.PathLike,
    models: Sequence[str] | None = None,
    seeds: Sequence[int] = tuple(range(SCREEN_SEEDS)),
    tasks: Sequence[str] | None = None,
    overrides: dict[str, dict[str, Any]] | None = None,
    name: str | None = None,
    hyperparams_file: str | os.PathLike | None = None,
    checkpoint_freq: int = 10_000,
    stop_after: int | None = None,
) -> list[RunSpec]:
    """
    The runs of a screen: each model on each task of the suite with the task's budget and warm-up (the
    ``learning_starts`` of every model, see :class:`ScreenTask`), evaluated every :data:`SCREEN_EVAL_FREQ` steps on
    :data:`SCREEN_EVAL_EPISODES` episodes, into ``root/<env_id>/<model>/seed_<n>``. A run is the one
    ``run --env ENV --suite benchmark --models MODEL --timesteps BUDGET --eval-freq 5000
    --hyperparams MODEL:learning_starts=WARMUP --out root/ENV`` builds, so the two share their runs.

    :param root: the screen's folder (one experiment folder per task)
    :param models: the variants (default: ``soup_defaults``); with ``name``, exactly one
    :param seeds: the seeds
    :param tasks: narrow the suite to these env ids
    :param overrides: from :func:`parse_overrides`; they may not set what a task fixes (:data:`SCREEN_FIXED_KEYS`)
    :param name: store the runs as this model (see :func:`build_grid`): a candidate, one named SOUP setting
    :param hyperparams_file: see :func:`build_grid`
    :param checkpoint_freq: see :class:`RunSpec`
    :param stop_after: see :class:`RunSpec`
    :return: the runs, task by task (then model, then seed)
    """
    names = list(models) if models else ["soup_defaults"]
    overrides = overrides or {}
    fixed = sorted({f"{target}:{key}" for target, values in overrides.items() for key in values if key in SCREEN_FIXED_KEYS})
    if fixed:
        raise ValueError(f"a screen task fixes {', '.join(SCREEN_FIXED_KEYS)} for every model; remove {fixed}")
    specs = []
    for task in screen_tasks(tasks):
        warmup = {"learning_starts": task.learning_starts}
        # "*" for SOUP's and the paper's models, the variant's name for the RL Zoo's (which take no "*" override)
        task_overrides = {target: dict(values) for target, values in overrides.items()}
        task_overrides["*"] = {**task_overrides.get("*", {}), **warmup}
        for variant_name in names:
            task_overrides[variant_name] = {**task_overrides.get(variant_name, {}), **warmup}
        specs += build_grid(
            task.env_id,
            Path(root) / task.env_id,
            suite=SCREEN_SUITE,
            models=names,
            seeds=seeds,
            timesteps=task.timesteps,
            overrides=task_overrides,
            hyperparams_file=hyperparams_file,
            checkpoint_freq=checkpoint_freq,
            stop_after=stop_after,
            eval_freq=SCREEN_EVAL_FREQ,
            eval_episodes=SCREEN_EVAL_EPISODES,
            name=name,
        )
    return specs
