"""
A goal-conditioned environment for the RL Zoo + HER tests, registered on import as ``SOUPBitFlipping-v0``: SB3's
``BitFlippingEnv`` with continuous actions (Box(-1, 1, (4,)); a bit flips where the action is > 0), 4 bits, episodes of
4 steps, Dict observations (``observation``, ``achieved_goal``, ``desired_goal``) and ``compute_reward``, so that
``python -m rl_zoo3.train --gym-packages goal_env`` finds it when ``tests/`` is on the path (no panda-gym needed).
"""

import gymnasium as gym

gym.register(
    "SOUPBitFlipping-v0",
    entry_point="stable_baselines3.common.envs:BitFlippingEnv",
    kwargs=dict(n_bits=4, continuous=True, max_steps=4),
)
