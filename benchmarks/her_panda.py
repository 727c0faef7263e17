"""
SOUP + HER against SB3's DDPG + HER and TD3 + HER on panda-gym's PandaReach-v3 (a goal-conditioned robot arm task
with a sparse reward: -1 until the gripper is within 5 cm of the goal), at the same budget and settings.

One run per call; each writes a JSON of its deterministic evaluations (success rate and mean return every
``--eval-freq`` steps, over ``--eval-episodes`` episodes of a separate env) and its wall time. The settings are the
RL Zoo's PandaReach entry (``rl_zoo3/hyperparams/tqc.yml``: gamma 0.95, learning rate 1e-3, batch 256, 1000 random
steps, HER with 4 "future" goals, 64-unit networks) for the three algorithms, with N(0, 0.1) exploration noise (SOUP's
built-in noise, the Zoo's for DDPG and TD3) and without the Zoo's observation normalisation.

Usage (``pip install "sb3-soup[her]"`` for panda-gym)::

    python benchmarks/her_panda.py --algo soup --seed 0 --timesteps 10000 --out docs/results/her/soup_0.json
    for algo in soup ddpg td3; do for seed in 0 1 2; do
        python benchmarks/her_panda.py --algo $algo --seed $seed --timesteps 10000 --out docs/results/her/${algo}_$seed.json
    done; done
    python benchmarks/her_panda.py --table docs/results/her/*.json     # the markdown table of docs/results.md
"""

import argparse
import glob
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from typing import Any

ENV_ID = "PandaReach-v3"
COMMON: dict[str, Any] = dict(
    learning_rate=1e-3, batch_size=256, gamma=0.95, learning_starts=1000, buffer_size=1_000_000, tau=0.005
)
HER_KWARGS = dict(n_sampled_goal=4, goal_selection_strategy="future")
MLP = [64, 64]  # the Zoo's PandaReach networks
# the critic as measured, the action at its second layer (stated, so that the defaults' critic does not change the benchmark)
SOUP_ARCH = dict(pi_body=[64], pi_head=[64], qf_body=[64, 64], qf_head=[64], qf_action_layer=1)


def make_model(algo: str, env: Any, seed: int) -> Any:
    """The algorithm with HER and the shared settings."""
    import numpy as np
    from stable_baselines3 import DDPG, TD3, HerReplayBuffer
    from stable_baselines3.common.noise import NormalActionNoise

    from sb3_soup import SOUP

    kwargs = dict(COMMON, replay_buffer_class=HerReplayBuffer, replay_buffer_kwargs=dict(HER_KWARGS), seed=seed, verbose=0)
    n_actions = env.action_space.shape[0]
    noise = NormalActionNoise(np.zeros(n_actions), 0.1 * np.ones(n_actions))
    if algo == "soup":  # SOUP's default noise is N(0, 0.1) as well (a DecayingNormalActionNoise of decay 1)
        soup_kwargs = dict(critic_learning_rate=COMMON["learning_rate"], policy_kwargs=dict(net_arch=SOUP_ARCH))
        return SOUP("MultiInputPolicy", env, **soup_kwargs, **kwargs)
    algo_class = {"ddpg": DDPG, "td3": TD3}[algo]
    return algo_class("MultiInputPolicy", env, action_noise=noise, policy_kwargs=dict(net_arch=MLP), **kwargs)


def scheme(model: Any) -> dict[str, Any]:
    """SOUP's training scheme, which its defaults set (recorded: the defaults changed in 0.2.0)."""
    from sb3_soup.presets import PAPER_UPDATE

    return {name: getattr(model, name) for name in PAPER_UPDATE}


def run(algo: str, seed: int, timesteps: int, eval_freq: int, eval_episodes: int) -> dict[str, Any]:
    import panda_gym  # noqa: F401  (registers the Panda envs)
    import torch as th
    from stable_baselines3.common.callbacks import EvalCallback
    from stable_baselines3.common.env_util import make_vec_env

    th.set_num_threads(1)
    env = make_vec_env(ENV_ID, n_envs=1, seed=seed)
    eval_env = make_vec_env(ENV_ID, n_envs=1, seed=10_000 + seed)
    model = make_model(algo, env, seed)
    with tempfile.TemporaryDirectory() as log_path:  # EvalCallback keeps the success rates only with a log_path
        evaluations = EvalCallback(eval_env, eval_freq=eval_freq, n_eval_episodes=eval_episodes, log_path=log_path, verbose=0)
        start, start_cpu = time.time(), time.process_time()
        model.learn(timesteps, callback=evaluations)
        wall_time, cpu_time = time.time() - start, time.process_time() - start_cpu
    rows = [
        dict(timesteps=int(step), success_rate=statistics.fmean(successes), mean_return=statistics.fmean(returns))
        for step, successes, returns in zip(
            evaluations.evaluations_timesteps, evaluations.evaluations_successes, evaluations.evaluations_results
        )
    ]
    training_success = list(model.ep_success_buffer)
    return dict(
        env=ENV_ID,
        algo=algo,
        seed=seed,
        timesteps=timesteps,
        eval_freq=eval_freq,
        eval_episodes=eval_episodes,
        settings=dict(COMMON, her=HER_KWARGS, net_arch=SOUP_ARCH if algo == "soup" else MLP, action_noise="N(0, 0.1)")
        | (scheme(model) if algo == "soup" else {}),
        evaluations=rows,
        final_success_rate=rows[-1]["success_rate"] if rows else None,
        training_success_rate_last_100_episodes=statistics.fmean(training_success) if training_success else None,
        wall_time_s=round(wall_time, 1),
        cpu_time_s=round(cpu_time, 1),  # of this process: the wall time also counts the machine's other load
        machine=dict(platform=platform.platform(), cpus=os.cpu_count(), torch_threads=1, python=sys.version.split()[0]),
    )


def table(paths: list[str]) -> str:
    """Markdown table: per algorithm, each seed's success rate at each evaluation step, then the mean."""
    runs = [json.load(open(path)) for path in sorted(paths)]
    by_algo: dict[str, list[dict[str, Any]]] = {}
    for result in runs:
        by_algo.setdefault(result["algo"], []).append(result)
    steps = sorted({row["timesteps"] for result in runs for row in result["evaluations"]})
    lines = [
        "| algorithm | seed | " + " | ".join(f"{step / 1000:g}k" for step in steps) + " | wall time (s) |",
        "|---" * (len(steps) + 3) + "|",
    ]
    for algo in ("soup", "ddpg", "td3"):
        results = sorted(by_algo.get(algo, []), key=lambda result: result["seed"])
        for result in results:
            rates = {row["timesteps"]: row["success_rate"] for row in result["evaluations"]}
            cells = " | ".join(f"{rates[step]:.2f}" if step in rates else "-" for step in steps)
            lines.append(f"| {algo.upper()} + HER | {result['seed']} | {cells} | {result['wall_time_s']:.0f} |")
        if len(results) > 1:
            rates_at = [[row["success_rate"] for res in results for row in res["evaluations"] if row["timesteps"] == step]
                        for step in steps]  # fmt: skip
            cells = " | ".join(f"**{statistics.fmean(rates):.2f}**" if rates else "-" for rates in rates_at)
            walls = statistics.fmean(result["wall_time_s"] for result in results)
            lines.append(f"| **{algo.upper()} + HER** | mean | {cells} | {walls:.0f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", choices=("soup", "ddpg", "td3"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timesteps", type=int, default=10_000)
    parser.add_argument("--eval-freq", type=int, default=1000)
    parser.add_argument("--eval-episodes", type=int, default=20)
    parser.add_argument("--out", help="the run's JSON")
    parser.add_argument("--table", nargs="+", metavar="JSON", help="print the markdown table of these runs' JSON files")
    args = parser.parse_args()
    if args.table:
        print(table([path for pattern in args.table for path in glob.glob(pattern)]))
        return
    if args.algo is None or args.out is None:
        parser.error("--algo and --out are needed to run (or --table to tabulate)")
    result = run(args.algo, args.seed, args.timesteps, args.eval_freq, args.eval_episodes)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as file:
        json.dump(result, file, indent=2)
    print(json.dumps({key: result[key] for key in ("algo", "seed", "final_success_rate", "wall_time_s")}))


if __name__ == "__main__":
    main()
