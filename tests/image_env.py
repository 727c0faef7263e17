"""
A tiny image-observation environment for the CnnPolicy tests, registered on import as ``SOUPTinyImage-v0``
(channel-last (36, 36, 3) uint8 images, NatureCNN's smallest) and ``SOUPTinyImageChannelFirst-v0`` ((3, 36, 36)), so that
``python -m rl_zoo3.train --gym-packages image_env`` finds it when ``tests/`` is on the path.
"""

import gymnasium as gym
import numpy as np
from gymnasium import spaces

SIZE = 36  # NatureCNN's smallest input


class TinyImageEnv(gym.Env):
    """
    Each step shows an image whose brightness encodes a target in [-1, 1]; the reward is minus the distance of the
    action's first coordinate (scaled to [-1, 1]) to it. Episodes of 10 steps. Actions in [-2, 2] x [0, 1], so that
    the rescaling to the action bounds matters.

    :param channel_first: images of shape (3, 36, 36) instead of (36, 36, 3)
    """

    def __init__(self, channel_first: bool = False):
        shape = (3, SIZE, SIZE) if channel_first else (SIZE, SIZE, 3)
        self.observation_space = spaces.Box(0, 255, shape, np.uint8)
        self.action_space = spaces.Box(np.array([-2.0, 0.0], np.float32), np.array([2.0, 1.0], np.float32))
        self.t = 0
        self.target = 0.0

    def _observation(self) -> np.ndarray:
        self.target = float(self.np_random.uniform(-1, 1))
        image = self.np_random.integers(0, 40, self.observation_space.shape, dtype=np.uint8)  # noise
        return image + np.uint8(round((self.target + 1) * 100))  # brightness: 0..200 + noise

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._observation(), {}

    def step(self, action):
        self.t += 1
        reward = -abs(float(action[0]) / 2 - self.target)
        return self._observation(), reward, False, self.t >= 10, {}


gym.register("SOUPTinyImage-v0", entry_point=f"{__name__}:TinyImageEnv")
gym.register("SOUPTinyImageChannelFirst-v0", entry_point=f"{__name__}:TinyImageEnv", kwargs=dict(channel_first=True))
