"""
The training run that tests/test_resume.py kills with SIGKILL and resumes: run as a script, it trains SOUP on
Pendulum-v1 with SB3's CheckpointCallback (prefix "sb3") and sb3-soup's ResumableCheckpointCallback (prefix
"rl_model") until it is killed.
"""

import sys

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import CheckpointCallback

from sb3_soup import SOUP, DecayingNormalActionNoise
from sb3_soup.checkpoint import ResumableCheckpointCallback

TINY = dict(net_arch=dict(pi_body=[16], pi_head=[16], qf_body=[16, 16], qf_head=[16]))
KWARGS = dict(
    n_heads=3,
    learning_starts=40,
    batch_size=16,
    buffer_size=2000,
    policy_kwargs=TINY,
    seed=11,
)
NOISE = dict(decay=0.995, sigma_min=0.05)
SAVE_FREQ = 60


def make_model() -> SOUP:
    """The run's model (adaptive confidence: a REINFORCE network, its Adam state and a reward baseline)."""
    noise = DecayingNormalActionNoise(np.zeros(1), np.full(1, 0.5), **NOISE)  # a decaying noise: its schedule must resume
    return SOUP("MlpPolicy", "Pendulum-v1", action_noise=noise, **KWARGS)


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
