"""
SOUP learns with its defaults: Pendulum-v1 within 20,000 steps, mean evaluation return >= -250 averaged over 2 seeds.
Only the budget is set (the steps, and the demo's PENDULUM_SETTINGS: learning_starts, so that the warm-up is a small
part of them; test_zoo checks that soup.yml's entry, and so PENDULUM_SETTINGS, holds nothing but the budget), so that
a bad default cannot hide behind settings tuned for the test.
"""

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

TIMESTEPS = 20_000
SEEDS = (0, 1)


def train_and_evaluate(seed: int) -> float:
    import torch as th
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    from sb3_soup import SOUP
    from sb3_soup.demo import PENDULUM_SETTINGS

    th.set_num_threads(1)
    model = SOUP("MlpPolicy", "Pendulum-v1", seed=seed, **PENDULUM_SETTINGS)
    model.learn(TIMESTEPS)
    mean_return, _ = evaluate_policy(model, make_vec_env("Pendulum-v1", seed=1000 + seed), n_eval_episodes=10)
    return float(mean_return)


@pytest.mark.slow
@pytest.mark.timeout(3000)
def test_soup_learns_pendulum_within_20k_steps():
    with ProcessPoolExecutor(max_workers=len(SEEDS), mp_context=multiprocessing.get_context("spawn")) as pool:
        returns = list(pool.map(train_and_evaluate, SEEDS))
    print(f"Pendulum-v1, {TIMESTEPS} steps, mean evaluation return per seed: {returns}, average {np.mean(returns):.1f}")
    assert np.mean(returns) >= -250
