"""sb3-soup: SOUP (Self-Adaptive Double Bootstrapped DDPG) for Stable-Baselines3."""

import os

with open(os.path.join(os.path.dirname(__file__), "version.txt")) as file_handler:
    __version__ = file_handler.read().strip()

__all__ = ["__version__"]
