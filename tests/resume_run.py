"""
The training run that tests/test_resume.py kills with SIGKILL and resumes: run as a script, it trains SOUP on
Pendulum-v1 with SB3's CheckpointCallback (prefix "sb3") and sb3-soup's ResumableCheckpointCallback (prefix
"rl_model") until it is killed.
"""

import sys

import torch as th
from stable_baselines3.common.callbacks import CheckpointCallback

from sb3_soup import SOUP
from sb3_soup.checkpoint import ResumableCheckpointCallback

TINY = dict(net_arch=dict(pi_body=[16], pi_head=[16], qf_body=[16, 16], qf_head=[16]))
KWARGS = dict(
    n_heads=3,
    learning_starts=40,
    batch_size=16,
    buffer_size=2000,
    noise_std=0.5,
    noise_decay=0.995,
    noise_std_min=0.05,
    policy_kwargs=TINY,
    seed=11,
)
SAVE_FREQ = 60


def make_model() -> SOUP:
    """The run's model (adaptive confidence: a REINFORCE network, its Adam state and a reward baseline)."""
    return SOUP("MlpPolicy", "Pendulum-v1", **KWARGS)


if __name__ == "__main__":
    th.set_num_threads(1)
    save_path = sys.argv[1]
    make_model().learn(
        1_000_000,
        callback=[
            ResumableCheckpointCallback(SAVE_FREQ, save_path),
            CheckpointCallback(SAVE_FREQ, save_path, name_prefix="sb3", save_replay_buffer=True),
        ],
    )
