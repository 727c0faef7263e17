"""
Throughput benchmark of SOUP against SB3's DDPG and TD3 (issue 5: K heads must not make SOUP K times slower).

Every (configuration, repeat) runs in a fresh subprocess with one torch thread; the configurations are interleaved
(repeat 1 of every configuration, then repeat 2, ...) so that a change of machine load hits them all alike; the table
reports medians over the repeats and each row's ratio to DDPG measured in the same run (the median over the repeats
of the ratio to DDPG's run in the same repeat), and the same ratio to SB3's default TD3 (``x TD3``: net_arch
[400, 300], the RL Zoo's and the screening suite's TD3; the ``td3`` row is TD3 at DDPG's [256, 256], like for like).

Measured per configuration (Hopper-v4, ``train_freq=1``, ``gradient_steps=1``):

- ``steps_per_s``: env-steps per second while training (after ``learning_starts`` and a few warm-up updates),
  over a time window; ``cpu_steps_per_s`` the same per second of the process's CPU time (``time.process_time``),
  which other processes' load on a shared machine does not stretch (``CPU x TD3``, ``cpu_speed_ratio_td3``: the
  paired ratio to SB3's TD3 by it);
- ``step_ms``, ``act_ms``, ``train_ms``, ``confidence_ms``: where an env-step's time goes over that window: in all,
  in choosing the action (``_sample_action``: SOUP's E-action, SB3's actor and noise), in the gradient step
  (``train``), and within it in SOUP's confidence update (eq. 8; 0 for SB3); the rest is the env, the buffer, callbacks;
- ``predict_1_ms`` / ``predict_8_ms``: deterministic ``predict`` latency for one observation and for a batch of 8;
- ``train_gflop``: analytic FLOP count of one gradient step (see :func:`train_flops`);
- ``peak_rss_mb`` (``--memory`` rows): peak RSS of a process holding a 1e6-transition replay buffer whose arrays are
  written (filled, as a full buffer would be) after a few training steps.

Usage::

    python benchmarks/throughput.py --out throughput.json            # full table (about 20 min on 2 shared cores)
    python benchmarks/throughput.py --quick --out quick.json         # a few rows, short windows (a smoke test)
    python benchmarks/throughput.py --device cuda --out gpu.json     # the same table on a GPU
    # a training scheme at K=5 against DDPG and TD3 (rows "soup K=5 NAME b...")
    python benchmarks/throughput.py --only td3 crit-redq --out scheme.json \
        --scheme crit-redq:train_heads=all_critics,target_q=redq,target_policy_noise=0.2,policy_delay=2
    # the screen's candidates (their names; those that set policy_kwargs are left out)
    python benchmarks/throughput.py --batch-sizes 256 --memory-buffer 0 --only td3 soup_ --out candidates.json \
        --candidates docs/results/screen/candidates.yml
"""

import argparse
import ast
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from typing import Any

ENV_ID = "Hopper-v4"
# Hopper-v4: 11-dimensional observations, 3-dimensional actions
OBS_DIM, ACT_DIM = 11, 3
DDPG_ARCH = [256, 256]
# SB3's TD3 default and the RL Zoo's (the screening suite's TD3): the "td3-sb3" rows, the reference of "x TD3"
TD3_SB3_ARCH = [400, 300]
# The paper's sizes (sb3_soup.policies.DEFAULT_NET_ARCH), where each checkout's default puts the action (a --before
# checkout may have another default)
SOUP_ARCH = dict(pi_body=[256], pi_head=[128], qf_body=[256, 256], qf_head=[128])
# Where SOUP's critic takes the action, for the FLOP count: sb3_soup.policies.DEFAULT_ACTION_LAYER (tests/test_benchmark.py
# checks it), 1, the paper's, at the second layer, after which the rest of the body runs once per action scored (0:
# its input, where the whole body runs once per action); written out as PAPER_SCHEME is
SOUP_ACTION_LAYER = 1


def _single_thread() -> None:
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = "1"


# What a SOUP row trains besides K and its confidence (the paper's update, unless a row says otherwise):
# sb3_soup.presets.PAPER_UPDATE (tests/test_benchmark.py checks it), written out because a --before child imports
# another checkout's sb3_soup, which may predate that constant (and sb3_soup imports torch, after _single_thread)
PAPER_SCHEME: dict[str, Any] = dict(train_heads="active", target_q="own", policy_delay=1, target_policy_noise=0.0)


def soup_defaults() -> dict[str, Any]:
    """SOUP's default training scheme and confidence (the ``defaults`` rows)."""
    import inspect

    from sb3_soup import SOUP
    from sb3_soup.presets import DEFAULT_CONFIDENCE

    parameters = inspect.signature(SOUP.__init__).parameters
    return dict({key: parameters[key].default for key in PAPER_SCHEME}, confidence=DEFAULT_CONFIDENCE)


def config_name(config: dict[str, Any]) -> str:
    if config["algo"] == "td3-sb3":
        return f"td3 {TD3_SB3_ARCH} (SB3's) b{config['batch_size']}"
    if config["algo"] != "soup":
        return f"{config['algo']} b{config['batch_size']}"
    if config.get("defaults"):
        name = f"soup K={config['n_heads']} defaults b{config['batch_size']}"
    elif "scheme_name" in config:
        name = f"soup K={config['n_heads']} {config['scheme_name']} b{config['batch_size']}"
    else:
        name = f"soup K={config['n_heads']} {config['train_heads']} {config['confidence']} b{config['batch_size']}"
    return name + (" (before)" if config.get("before") else "")


def scheme(config: dict[str, Any]) -> dict[str, Any]:
    """A SOUP row's training scheme and confidence."""
    if config.get("defaults"):
        return soup_defaults()
    if "scheme_name" in config:  # a named scheme (--scheme): SOUP's defaults with these settings
        return {**soup_defaults(), **config["scheme"]}
    return {**PAPER_SCHEME, "train_heads": config["train_heads"], "confidence": config["confidence"]}


def check_scheme(name: str, settings: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """A scheme's settings are SOUP's arguments besides the networks' (whose FLOPs the table counts at the paper's sizes)."""
    if "policy_kwargs" in settings:
        raise ValueError(f"scheme {name}: policy_kwargs are not measured (the table counts the paper's network sizes)")
    return name, settings


def parse_scheme(text: str) -> tuple[str, dict[str, Any]]:
    """``NAME:key=value,key=value`` (values as Python literals, else strings; ``n_heads`` sets K) -> (NAME, settings)."""
    name, _, settings = text.partition(":")
    if not name or not settings:
        raise argparse.ArgumentTypeError(f"--scheme takes NAME:key=value,key=value..., got {text!r}")
    scheme_settings = {}
    for item in re.split(r",(?![^\[(]*[\])])", settings):  # the commas outside brackets
        key, _, value = item.partition("=")
        try:
            scheme_settings[key.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            scheme_settings[key.strip()] = value.strip()
    try:
        return check_scheme(name, scheme_settings)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from error


def read_schemes(path: str, only: list[str] | None) -> list[tuple[str, dict[str, Any]]]:
    """The screen's candidates (``sb3_soup.experiments.grid.read_candidates``) as schemes, but those that set networks."""
    from sb3_soup.experiments.grid import read_candidates

    schemes = []
    for name, settings in read_candidates(path, only).items():
        if "policy_kwargs" in settings and not only:
            print(f"not measured: {name} (policy_kwargs)", file=sys.stderr)
            continue
        schemes.append(check_scheme(name, settings))
    return schemes


def make_configs(
    quick: bool, batch_sizes: list[int], schemes: list[tuple[str, dict[str, Any]]] | None = None
) -> list[dict[str, Any]]:
    """
    The table's rows: DDPG, TD3, then SOUP for K in (1, 5, 10), active/all heads with the paper's update, confidence
    none/adaptive, SOUP's defaults at K=5, and each named scheme (SOUP's defaults with its settings) at K=5.
    """
    configs: list[dict[str, Any]] = []
    for batch_size in batch_sizes:
        baselines = ["ddpg"] if quick else ["ddpg", "td3", "td3-sb3"]
        configs += [dict(algo=algo, batch_size=batch_size) for algo in baselines]
        configs.append(dict(algo="soup", batch_size=batch_size, n_heads=5, defaults=True))
        for scheme_name, settings in schemes or []:
            n_heads = settings.get("n_heads", 5)
            scheme_settings = {key: value for key, value in settings.items() if key != "n_heads"}
            configs.append(
                dict(algo="soup", batch_size=batch_size, n_heads=n_heads, scheme_name=scheme_name, scheme=scheme_settings)
            )
        heads = (10,) if quick else (1, 5, 10)
        for n_heads in heads:
            for train_heads in ("active", "all"):
                for confidence in ("none", "adaptive"):
                    if quick and (train_heads, confidence) == ("all", "none"):
                        continue
                    configs.append(
                        dict(
                            algo="soup",
                            batch_size=batch_size,
                            n_heads=n_heads,
                            train_heads=train_heads,
                            confidence=confidence,
                        )
                    )
    return configs


# ----- FLOP count -------------------------------------------------------------------------------------------------


def baseline_arch(config: dict[str, Any]) -> list[int]:
    """The hidden layers of an SB3 baseline row: SB3's default TD3's for "td3-sb3", DDPG's for the others."""
    return TD3_SB3_ARCH if config["algo"] == "td3-sb3" else DDPG_ARCH


def _mlp_macs(sizes: list[int]) -> int:
    """Multiply-accumulates of one sample through linear layers of these sizes."""
    return sum(sizes[i] * sizes[i + 1] for i in range(len(sizes) - 1))


def _critic_body_macs(action_layer: int | None) -> tuple[int, int]:
    """
    Multiply-accumulates of SOUP's critic body for one observation: the part computed once per observation, and the
    part computed once per action it scores (the action's projection in the layer it joins, and the layers after).

    :param action_layer: where the action joins (``qf_action_layer``; None: :data:`SOUP_ACTION_LAYER`)
    """
    body = SOUP_ARCH["qf_body"]
    if (SOUP_ACTION_LAYER if action_layer is None else action_layer) == 1:
        return OBS_DIM * body[0] + body[0] * body[1], ACT_DIM * body[1] + _mlp_macs(body[1:])
    return OBS_DIM * body[0], ACT_DIM * body[0] + _mlp_macs(body)


def train_flops(config: dict[str, Any], action_layer: int | None = None) -> float:
    """
    FLOPs of one gradient step (critic and actor updates, targets), counted from the layer sizes: a forward pass is
    2 FLOPs per multiply-accumulate and per sample; a pass that needs the weights' gradients costs 3 forward passes,
    one that only propagates the gradient to its input (the critic under the actor loss in SOUP, which calls
    ``backward(inputs=actor parameters)``) 2. SB3's DDPG/TD3 backpropagate the actor loss into the critic's weights
    too (3). Optimizer and soft updates (proportional to the parameter count, not the batch) are left out.

    :param config: the row
    :param action_layer: where SOUP's critic takes the action (None: :data:`SOUP_ACTION_LAYER`)
    """
    batch = config["batch_size"]
    if config["algo"] in ("ddpg", "td3", "td3-sb3"):
        arch = baseline_arch(config)
        actor = _mlp_macs([OBS_DIM, *arch, ACT_DIM])
        critic = _mlp_macs([OBS_DIM + ACT_DIM, *arch, 1])
        n_critics = 1 if config["algo"] == "ddpg" else 2
        # target: actor + critics forward; critic loss: critics forward+backward
        macs = actor + n_critics * critic + 3 * n_critics * critic
        if config["algo"] == "ddpg":
            macs += 3 * actor + 3 * critic  # actor loss every step
        else:
            macs += (3 * actor + 3 * critic) / 2  # policy_delay=2: actor loss every other step (through Q1)
        return 2.0 * batch * macs
    k = config["n_heads"]
    update = scheme(config)
    a_body = _mlp_macs([OBS_DIM, *SOUP_ARCH["pi_body"]])
    a_head = _mlp_macs([SOUP_ARCH["pi_body"][-1], *SOUP_ARCH["pi_head"], ACT_DIM])
    c_obs, c_act = _critic_body_macs(action_layer)
    c_head = _mlp_macs([SOUP_ARCH["qf_body"][-1], *SOUP_ARCH["qf_head"], 1])
    n = 1 if update["train_heads"] == "active" else k  # critic heads (pairs) trained by the step
    m = k if update["train_heads"] == "all" else 1  # actor heads trained when the actor is
    target_heads = 2 if update["target_q"] in ("min_pair", "redq") and k > 1 else 1  # target critic heads per pair
    target = a_body + n * a_head + c_obs + n * (c_act + target_heads * c_head)
    critic = 3 * (c_obs + c_act + n * c_head)  # one action per sample, n heads on the same features
    actor = 3 * (a_body + m * a_head) + 2 * (c_obs + m * (c_act + c_head))  # critic: gradient to its input only
    return 2.0 * batch * (target + critic + actor / update["policy_delay"])


def predict_flops(config: dict[str, Any], action_layer: int | None = None) -> float:
    """
    FLOPs of a deterministic ``predict`` for one observation. DDPG: its actor. SOUP: every actor head proposes a
    candidate, every critic head scores every candidate (K x K head evaluations, the E-Critic's matrix ``V``), plus the
    confidence network (adaptive).

    :param config: the row
    :param action_layer: where SOUP's critic takes the action (None: :data:`SOUP_ACTION_LAYER`)
    """
    if config["algo"] in ("ddpg", "td3", "td3-sb3"):
        return 2.0 * _mlp_macs([OBS_DIM, *baseline_arch(config), ACT_DIM])
    k = config["n_heads"]
    actor = _mlp_macs([OBS_DIM, *SOUP_ARCH["pi_body"]]) + k * _mlp_macs(
        [SOUP_ARCH["pi_body"][-1], *SOUP_ARCH["pi_head"], ACT_DIM]
    )
    c_obs, c_act = _critic_body_macs(action_layer)
    critic = c_obs + k * c_act + k * k * _mlp_macs([SOUP_ARCH["qf_body"][-1], *SOUP_ARCH["qf_head"], 1])
    confidence = _mlp_macs([OBS_DIM, 256, 128, k]) if scheme(config)["confidence"] == "adaptive" and k > 1 else 0
    if k == 1:
        critic = 0  # one candidate: no scoring
    return 2.0 * (actor + critic + confidence)


# ----- the child process ------------------------------------------------------------------------------------------


def _make_model(config: dict[str, Any], device: str, buffer_size: int, learning_starts: int, seed: int) -> Any:
    from stable_baselines3 import DDPG, TD3

    from sb3_soup import SOUP

    common = dict(
        buffer_size=buffer_size,
        learning_starts=learning_starts,
        batch_size=config["batch_size"],
        train_freq=1,
        gradient_steps=1,
        seed=seed,
        device=device,
        verbose=0,
    )
    if config["algo"] in ("ddpg", "td3", "td3-sb3"):
        algo = DDPG if config["algo"] == "ddpg" else TD3
        return algo("MlpPolicy", ENV_ID, policy_kwargs=dict(net_arch=list(baseline_arch(config))), **common)
    return SOUP(
        "MlpPolicy", ENV_ID, n_heads=config["n_heads"], policy_kwargs=dict(net_arch=SOUP_ARCH), **scheme(config), **common
    )


def _predict_latency_ms(model: Any, n_obs: int, duration: float) -> float:
    import numpy as np

    rng = np.random.default_rng(0)
    obs = rng.normal(size=(OBS_DIM,) if n_obs == 1 else (n_obs, OBS_DIM)).astype(np.float32)
    for _ in range(20):
        model.predict(obs, deterministic=True)
    times = []
    deadline = time.perf_counter() + duration
    while time.perf_counter() < deadline or len(times) < 50:
        start = time.perf_counter()
        model.predict(obs, deterministic=True)
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def _timed(method: Any, spent: dict[str, float], part: str, stamps: list[float]) -> Any:
    """``method``, adding the seconds of each call made while the window is open (``stamps`` begun) to ``spent[part]``."""

    def timed(*args: Any, **kwargs: Any) -> Any:
        start = time.perf_counter()
        result = method(*args, **kwargs)
        if stamps:
            spent[part] += time.perf_counter() - start
        return result

    return timed


def measure_speed(config: dict[str, Any], device: str, window: float, learning_starts: int, seed: int) -> dict[str, Any]:
    """Train past ``learning_starts`` plus warm-up updates, then count env-steps over ``window`` seconds."""
    from stable_baselines3.common.callbacks import BaseCallback

    model = _make_model(config, device, buffer_size=100_000, learning_starts=learning_starts, seed=seed)
    warmup = 20
    model.learn(total_timesteps=learning_starts + warmup)

    class Window(BaseCallback):
        """Time stamps of the env-steps; stops the run once the window is over (one update between two stamps)."""

        def __init__(self) -> None:
            super().__init__()
            self.stamps: list[float] = []
            self.cpu_stamps: list[float] = []  # the process's CPU time: what other processes' load does not add to

        def _on_step(self) -> bool:
            self.stamps.append(time.perf_counter())
            self.cpu_stamps.append(time.process_time())
            return self.stamps[-1] - self.stamps[0] < window

    callback = Window()
    # where an env-step's time goes: the seconds inside these calls while the window is open
    spent = {"act": 0.0, "train": 0.0, "confidence": 0.0}
    timed = [(model, "_sample_action", "act"), (model, "train", "train")]
    strategy = getattr(model.policy, "confidence", None)  # SOUP's eq. 8 update, inside train
    if strategy is not None:
        timed.append((strategy, "update", "confidence"))
    for owner, method, part in timed:
        setattr(owner, method, _timed(getattr(owner, method), spent, part, callback.stamps))
    model.learn(total_timesteps=10**9, callback=callback, reset_num_timesteps=False)
    stamps = callback.stamps
    n_steps = len(stamps) - 1
    steps_per_s = n_steps / (stamps[-1] - stamps[0])
    return dict(
        steps_per_s=steps_per_s,
        cpu_steps_per_s=n_steps / (callback.cpu_stamps[-1] - callback.cpu_stamps[0]),
        n_steps=n_steps,
        step_ms=1e3 / steps_per_s,
        **{f"{part}_ms": 1e3 * seconds / n_steps for part, seconds in spent.items()},
        predict_1_ms=_predict_latency_ms(model, 1, duration=min(1.0, window / 4)),
        predict_8_ms=_predict_latency_ms(model, 8, duration=min(1.0, window / 4)),
        # where the critic takes the action (SOUP's; a checkout before the choice existed: the paper's second layer)
        qf_action_layer=getattr(model.critic, "action_layer", 1),
    )


def measure_memory(config: dict[str, Any], device: str, buffer_size: int, seed: int) -> dict[str, Any]:
    """Peak RSS with a ``buffer_size`` replay buffer whose arrays are written (as when full), after a few updates."""
    import resource

    import numpy as np

    model = _make_model(config, device, buffer_size=buffer_size, learning_starts=100, seed=seed)
    model.learn(total_timesteps=120)
    buffer = model.replay_buffer
    arrays = {name: value for name, value in vars(buffer).items() if isinstance(value, np.ndarray)}
    for value in arrays.values():
        value.fill(0)  # np.zeros allocates lazily: touch every page, as a full buffer does
    nbytes = {name: int(value.nbytes) for name, value in arrays.items()}
    masks = arrays.get("masks")
    return dict(
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,  # kB on Linux
        buffer_mb=sum(nbytes.values()) / 2**20,
        mask_mb=nbytes.get("masks", 0) / 2**20,
        mask_dtype=None if masks is None else str(masks.dtype),
    )


def child(args: argparse.Namespace) -> None:
    import torch as th

    th.set_num_threads(1)
    config = json.loads(args.child)
    if args.memory_buffer:
        result = measure_memory(config, args.device, args.memory_buffer, args.seed)
    else:
        result = measure_speed(config, args.device, args.window, args.learning_starts, args.seed)
    print("RESULT " + json.dumps(result), flush=True)


# ----- the parent: interleaved subprocesses, medians, table -------------------------------------------------------


def run_child(config: dict[str, Any], args: argparse.Namespace, seed: int, memory_buffer: int = 0) -> dict[str, Any]:
    command = [
        sys.executable,
        os.path.abspath(__file__),
        "--child",
        json.dumps(config),
        "--device",
        args.device,
        "--window",
        str(args.window),
        "--learning-starts",
        str(args.learning_starts),
        "--seed",
        str(seed),
        "--memory-buffer",
        str(memory_buffer),
    ]
    env = dict(os.environ)
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    if config.get("before"):
        # an older sb3_soup (a checkout's root folder) shadows the installed one in this child
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [args.before, env.get("PYTHONPATH")]))
    done = subprocess.run(command, capture_output=True, text=True, env=env, check=False)
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    if done.returncode != 0 or not lines:
        raise RuntimeError(f"{config_name(config)} failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULT ") :])


BREAKDOWN = ("step_ms", "act_ms", "train_ms", "confidence_ms")
"""An env-step's milliseconds: in all, choosing the action, the gradient step, and (SOUP) eq. 8's update within it."""


def _median(runs: list[dict[str, Any]], key: str) -> float:
    return float(statistics.median(run[key] for run in runs))


def summarize(configs: list[dict[str, Any]], speed: dict[str, list], memory: dict[str, list]) -> list[dict[str, Any]]:
    rows = []
    for config in configs:
        name = config_name(config)
        runs = speed[name]
        row: dict[str, Any] = dict(name=name, config=config, repeats=runs)
        for key in ("steps_per_s", "cpu_steps_per_s", "predict_1_ms", "predict_8_ms", *BREAKDOWN):
            row[key] = _median(runs, key)
        action_layer = runs[0].get("qf_action_layer")  # SOUP's critic as the row's checkout built it
        row["train_gflop"] = train_flops(config, action_layer) / 1e9
        row["predict_mflop"] = predict_flops(config, action_layer) / 1e6
        rows.append(row)
    for row in rows:
        batch_size = row["config"]["batch_size"]
        ddpg = next(r for r in rows if r["config"]["algo"] == "ddpg" and r["config"]["batch_size"] == batch_size)
        # paired: each repeat's ratio to DDPG's run of the same repeat (same stretch of machine load), then the median
        for key, ratio_key in (
            ("steps_per_s", "speed_ratio"),
            ("predict_1_ms", "predict_1_ratio"),
            ("predict_8_ms", "predict_8_ratio"),
        ):
            ratios = [run[key] / base[key] for run, base in zip(row["repeats"], ddpg["repeats"])]
            row[ratio_key] = float(statistics.median(ratios))
            row[ratio_key + "_per_repeat"] = ratios
            row[ratio_key + "_of_medians"] = row[key] / ddpg[key]
        row["flop_ratio"] = row["train_gflop"] / ddpg["train_gflop"]  # > 1: more arithmetic than DDPG per update
        td3 = next((r for r in rows if r["config"]["algo"] == "td3-sb3" and r["config"]["batch_size"] == batch_size), None)
        if td3 is not None:  # the same pairing against SB3's default TD3's run of each repeat
            for key, ratio_key in (("steps_per_s", "speed_ratio_td3"), ("cpu_steps_per_s", "cpu_speed_ratio_td3")):
                ratios = [run[key] / base[key] for run, base in zip(row["repeats"], td3["repeats"])]
                row[ratio_key] = float(statistics.median(ratios))
                row[ratio_key + "_per_repeat"] = ratios
        row["predict_flop_ratio"] = row["predict_mflop"] / ddpg["predict_mflop"]
    memory_rows = []
    for name, runs in memory.items():
        memory_rows.append(
            dict(
                name=name,
                repeats=runs,
                peak_rss_mb=_median(runs, "peak_rss_mb"),
                buffer_mb=runs[0]["buffer_mb"],
                mask_mb=runs[0]["mask_mb"],
                mask_dtype=runs[0]["mask_dtype"],
            )
        )
    if memory_rows:
        ddpg_rss = next(r["peak_rss_mb"] for r in memory_rows if r["name"].startswith("ddpg"))
        for row in memory_rows:
            row["rss_ratio"] = row["peak_rss_mb"] / ddpg_rss
    return rows + memory_rows


def print_table(rows: list[dict[str, Any]]) -> None:
    header = (
        f"{'configuration':<42} {'steps/s':>8} {'x DDPG':>7} {'x TD3':>6} {'CPU x TD3':>9} {'FLOP x':>7} {'1/FLOPx':>7} "
        f"{'pred1 ms':>9} {'x DDPG':>7} {'pred8 ms':>9} {'x DDPG':>7} {'pred FLOP x':>11}"
    )
    print(header)
    print("-" * len(header))
    for row in rows:
        if "steps_per_s" not in row:
            continue
        print(
            f"{row['name']:<42} {row['steps_per_s']:>8.1f} {row['speed_ratio']:>7.2f} "
            f"{row.get('speed_ratio_td3', float('nan')):>6.2f} {row.get('cpu_speed_ratio_td3', float('nan')):>9.2f} "
            f"{row['flop_ratio']:>7.2f} "
            f"{1 / row['flop_ratio']:>7.2f} {row['predict_1_ms']:>9.3f} {row['predict_1_ratio']:>7.2f} "
            f"{row['predict_8_ms']:>9.3f} {row['predict_8_ratio']:>7.2f} {row['predict_flop_ratio']:>11.1f}"
        )
    print()
    print(f"{'ms per env-step':<42} {'in all':>8} {'act':>7} {'train':>7} {'of which eq. 8':>15} {'the rest':>9}")
    for row in rows:
        if "steps_per_s" in row:
            rest = row["step_ms"] - row["act_ms"] - row["train_ms"]  # the env, the buffer, callbacks and logging
            print(
                f"{row['name']:<42} {row['step_ms']:>8.2f} {row['act_ms']:>7.2f} {row['train_ms']:>7.2f} "
                f"{row['confidence_ms']:>15.2f} {rest:>9.2f}"
            )
    memory_rows = [row for row in rows if "peak_rss_mb" in row]
    if memory_rows:
        print()
        print(f"{'memory (1e6 buffer, filled)':<42} {'peak RSS MB':>12} {'x DDPG':>7} {'buffer MB':>10} {'masks MB':>9} dtype")
        for row in memory_rows:
            print(
                f"{row['name']:<42} {row['peak_rss_mb']:>12.0f} {row['rss_ratio']:>7.2f} {row['buffer_mb']:>10.1f} "
                f"{row['mask_mb']:>9.1f} {row['mask_dtype']}"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a few rows, 1 repeat, short windows (smoke test)")
    parser.add_argument("--repeats", type=int, default=None, help="fresh processes per configuration (default 3)")
    parser.add_argument("--window", type=float, default=None, help="seconds of training timed per process (default 5)")
    parser.add_argument("--learning-starts", type=int, default=None, help="random steps before training (default 1024)")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1024, 256])
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--memory-buffer", type=int, default=None, help="buffer size of the memory rows (0: none)")
    parser.add_argument("--only", nargs="*", default=None, help="keep the configurations whose name contains one of these")
    parser.add_argument(
        "--before",
        default=None,
        help="root of another sb3_soup checkout (e.g. `git worktree add /tmp/before <commit>`): its SOUP rows are "
        "measured in the same run, marked (before)",
    )
    parser.add_argument(
        "--before-rows",
        nargs="+",
        default=["K=10 active adaptive", "K=10 all adaptive"],
        help="the SOUP configurations measured with --before (name substrings)",
    )
    parser.add_argument(
        "--scheme",
        type=parse_scheme,
        action="append",
        default=[],
        help="a named training scheme, NAME:key=value,... (SOUP's defaults with these settings), measured at K=5 unless "
        "it sets n_heads; repeatable",
    )
    parser.add_argument(
        "--candidates",
        default=None,
        help="the screen's candidates file (docs/results/screen/candidates.yml) as schemes (those without policy_kwargs)",
    )
    parser.add_argument("--candidates-only", nargs="+", default=None, help="with --candidates: these candidates only")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="write the results as JSON here")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    _single_thread()
    if args.child is not None:
        args.memory_buffer = args.memory_buffer or 0
        child(args)
        return

    repeats = args.repeats or (1 if args.quick else 3)
    args.window = args.window or (1.5 if args.quick else 5.0)
    args.learning_starts = args.learning_starts or (256 if args.quick else 1024)
    memory_buffer = args.memory_buffer if args.memory_buffer is not None else (20_000 if args.quick else 1_000_000)
    batch_sizes = [args.batch_sizes[0]] if args.quick else args.batch_sizes
    schemes = list(args.scheme) + (read_schemes(args.candidates, args.candidates_only) if args.candidates else [])
    configs = make_configs(args.quick, batch_sizes, schemes)
    if args.only:
        configs = [c for c in configs if c["algo"] == "ddpg" or any(s in config_name(c) for s in args.only)]
    if args.before:
        before = [c for c in configs if c["algo"] == "soup" and any(s in config_name(c) for s in args.before_rows)]
        configs += [dict(config, before=True) for config in before]
    memory_configs = []
    if memory_buffer:
        memory_configs = [
            dict(algo="ddpg", batch_size=256),
            dict(algo="soup", batch_size=256, n_heads=10, train_heads="active", confidence="adaptive"),
        ]

    speed: dict[str, list] = {config_name(c): [] for c in configs}
    memory: dict[str, list] = {config_name(c): [] for c in memory_configs}
    start = time.time()
    for repeat in range(repeats):
        # interleaved: every configuration once per repeat, in an order that rotates between repeats
        order = configs[repeat % len(configs) :] + configs[: repeat % len(configs)]
        for config in order:
            result = run_child(config, args, seed=args.seed + repeat)
            speed[config_name(config)].append(result)
            print(
                f"[{time.time() - start:6.0f}s] repeat {repeat + 1}/{repeats} {config_name(config):<42} "
                f"{result['steps_per_s']:7.1f} steps/s",
                flush=True,
            )
        for config in memory_configs:
            result = run_child(config, args, seed=args.seed + repeat, memory_buffer=memory_buffer)
            memory[config_name(config)].append(result)
            print(f"[{time.time() - start:6.0f}s] repeat {repeat + 1}/{repeats} memory {config_name(config)}", flush=True)

    rows = summarize(configs, speed, memory)
    print()
    print_table(rows)
    if args.out:
        import torch as th

        meta = dict(
            date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            machine=platform.platform(),
            processor=platform.processor() or platform.machine(),
            cpu_count=os.cpu_count(),
            load_average=os.getloadavg(),
            python=platform.python_version(),
            torch=th.__version__,
            device=args.device,
            env=ENV_ID,
            repeats=repeats,
            window_s=args.window,
            learning_starts=args.learning_starts,
            memory_buffer=memory_buffer,
            wall_s=time.time() - start,
        )
        with open(args.out, "w") as file:
            json.dump(dict(meta=meta, rows=rows), file, indent=1)
        print(f"\nwritten to {args.out}")


if __name__ == "__main__":
    main()
