"""
The main job on a small default: train SOUP on Pendulum-v1, print evaluation returns,
save the model and a learning-curve plot.

    python -m sb3_soup.demo --out demo_output
"""

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

# SOUP's defaults with Pendulum-v1's budget: 1000 random steps of the 20k (as the slow learning test trains)
PENDULUM_SETTINGS: dict[str, Any] = dict(learning_starts=1000)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description="Train SOUP, print evaluation returns, save the model and a learning curve.")
    parser.add_argument("--env", default="Pendulum-v1", help="Gymnasium environment id (Box actions)")
    parser.add_argument("--timesteps", type=int, default=15_000, help="training env-steps")
    parser.add_argument("--n-heads", type=int, default=5, help="number of bootstrapped heads K")
    parser.add_argument("--confidence", default="adaptive", help="none, fixed, decayed or adaptive")
    parser.add_argument("--eval-freq", type=int, default=2500, help="evaluate every N env-steps")
    parser.add_argument("--eval-episodes", type=int, default=5, help="episodes per evaluation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="demo_output", help="folder for the model, the plot and the logs")
    parser.add_argument("--no-progress-bar", action="store_true", help="hide the progress bar")
    return parser.parse_args(argv)


def plot_learning_curve(evaluations: Path, monitor_dir: Path, path: Path, title: str) -> None:
    """Evaluation returns (mean ± std) and training-episode returns against env-steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from stable_baselines3.common.monitor import load_results
    from stable_baselines3.common.results_plotter import ts2xy

    data = np.load(evaluations)
    timesteps, results = data["timesteps"], data["results"]
    fig, ax = plt.subplots(figsize=(7, 4))
    x, y = ts2xy(load_results(str(monitor_dir)), "timesteps")
    ax.plot(x, y, ".", alpha=0.35, color="gray", label="training episodes")
    mean, std = results.mean(axis=1), results.std(axis=1)
    ax.plot(timesteps, mean, "o-", color="C0", label="evaluation (deterministic)")
    ax.fill_between(timesteps, mean - std, mean + std, color="C0", alpha=0.2)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode return")
    ax.set_title(title)
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch as th
    from stable_baselines3.common.callbacks import EvalCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    from sb3_soup import SOUP

    th.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    env = make_vec_env(args.env, n_envs=1, seed=args.seed, monitor_dir=str(out / "monitor"))
    eval_env = make_vec_env(args.env, n_envs=1, seed=args.seed + 1000)
    settings = PENDULUM_SETTINGS if args.env.startswith("Pendulum") else {}
    model = SOUP("MlpPolicy", env, n_heads=args.n_heads, confidence=args.confidence, seed=args.seed, verbose=0, **settings)
    eval_callback = EvalCallback(
        eval_env, n_eval_episodes=args.eval_episodes, eval_freq=args.eval_freq, log_path=str(out), verbose=1, warn=False
    )
    print(f"Training SOUP (K={args.n_heads}, confidence={args.confidence}) on {args.env} for {args.timesteps} steps")
    start = time.time()
    model.learn(args.timesteps, callback=eval_callback, progress_bar=not args.no_progress_bar)
    train_time = time.time() - start

    model_path = out / "soup_model.zip"
    model.save(model_path)
    returns, _ = evaluate_policy(model, eval_env, n_eval_episodes=10, deterministic=True, return_episode_rewards=True)
    mean_return, std_return = float(np.mean(returns)), float(np.std(returns))
    plot_path = out / "learning_curve.png"
    plot_learning_curve(out / "evaluations.npz", out / "monitor", plot_path, f"SOUP (K={args.n_heads}) on {args.env}")

    evaluations = np.load(out / "evaluations.npz")
    print("\nEvaluation returns (deterministic E-actions):")
    for step, returns in zip(evaluations["timesteps"], evaluations["results"]):
        print(f"  step {int(step):>7}: {returns.mean():9.1f} ± {returns.std():6.1f}")
    print(f"Final evaluation over 10 episodes: {mean_return:.1f} ± {std_return:.1f}")
    print(f"Training took {train_time:.0f} s ({args.timesteps / train_time:.0f} env-steps/s)")
    print(f"Saved the model to {model_path} and the learning curve to {plot_path}")
    summary = dict(
        env=args.env,
        timesteps=args.timesteps,
        n_heads=args.n_heads,
        confidence=args.confidence,
        final_mean_return=float(mean_return),
        final_std_return=float(std_return),
        train_seconds=train_time,
        model=str(model_path),
        plot=str(plot_path),
    )
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


if __name__ == "__main__":
    main()
