"""
Train SOUP on Hopper-v4 with its defaults or the paper's settings, evaluating with EvalCallback and logging to
TensorBoard.

    python examples/train_hopper.py --timesteps 1000000
    python examples/train_hopper.py --timesteps 1000000 --n-heads 10 --settings paper
    tensorboard --logdir logs/tensorboard

A 1M-step run takes hours on a laptop CPU (about 20-50 env-steps/s with the defaults, which train every head pair
each step): use a bigger machine or
``--timesteps 50000`` for a first look. Every ``--eval-freq`` steps the E-actions are evaluated and the best model
is saved; checkpoints (replay buffer, random generators and environment state included) let an interrupted run,
even one killed, continue with ``--resume`` exactly as if it had not stopped (see docs/reliability.md).
"""

import argparse
from pathlib import Path

from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.env_util import make_vec_env

from sb3_soup import SOUP, paper_settings
from sb3_soup.checkpoint import ResumableCheckpointCallback, latest_checkpoint, load_checkpoint

# Both with the RL Zoo's MuJoCo warm-up: 10k uniformly random steps before learning
SETTINGS = {
    "defaults": lambda env: dict(learning_starts=10_000),  # SOUP's defaults (hyperparams/soup.yml's Hopper-v4 entry)
    # Section 5 of the paper (hyperparams/soup_paper.yml)
    "paper": lambda env: dict(paper_settings(env.action_space), learning_starts=10_000),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument("--env", default="Hopper-v4")
    parser.add_argument("--timesteps", type=int, default=1_000_000)
    parser.add_argument("--n-heads", type=int, default=5)
    parser.add_argument("--confidence", default="adaptive", choices=["none", "fixed", "decayed", "adaptive", "ucb"])
    parser.add_argument("--settings", default="defaults", choices=sorted(SETTINGS), help="SOUP's defaults or the paper's")
    parser.add_argument("--eval-freq", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--logdir", default="logs")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--resume", action="store_true", help="continue from the newest complete checkpoint in --logdir")
    args = parser.parse_args()

    logdir = Path(args.logdir)
    env = make_vec_env(args.env, n_envs=1, seed=args.seed)
    eval_env = make_vec_env(args.env, n_envs=1, seed=args.seed + 1000)
    checkpoints = logdir / "checkpoints"
    checkpoint = latest_checkpoint(checkpoints) if args.resume else None
    if args.resume and checkpoint is None:
        parser.error(f"no complete checkpoint in {checkpoints}")
    if checkpoint is not None:
        model = load_checkpoint(checkpoint, env, device=args.device, tensorboard_log=str(logdir / "tensorboard"))
        print(f"Resuming from step {checkpoint.step} ({checkpoint.model})")
    else:
        model = SOUP(
            "MlpPolicy",
            env,
            n_heads=args.n_heads,
            confidence=args.confidence,
            seed=args.seed,
            device=args.device,
            tensorboard_log=str(logdir / "tensorboard"),
            verbose=1,
            **SETTINGS[args.settings](env),
        )
    callbacks = [
        EvalCallback(
            eval_env,
            eval_freq=args.eval_freq,
            n_eval_episodes=10,
            best_model_save_path=str(logdir / "best"),
            log_path=str(logdir / "eval"),
        ),
        ResumableCheckpointCallback(save_freq=50_000, save_path=str(checkpoints), keep_last=2),
    ]
    remaining = args.timesteps - model.num_timesteps
    model.learn(remaining, callback=callbacks, progress_bar=True, reset_num_timesteps=checkpoint is None, tb_log_name="SOUP")
    model.save(logdir / "soup_hopper")


if __name__ == "__main__":
    main()
