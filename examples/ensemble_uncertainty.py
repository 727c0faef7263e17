"""
The ensemble's uncertainty: train SOUP briefly on Pendulum-v1, then ask it, with ``model.policy.ensemble_view``, how
sure it is of a few states: the states it visits, and states it never saw (spinning faster than Pendulum allows).

    python examples/ensemble_uncertainty.py --timesteps 5000

For every state it prints the executed action, the actor head that proposed it, the critic heads' mean value of that
action and their disagreement (``q_spread``, their std), and how far apart the actor heads' candidates are. A large
``q_spread`` says the critic heads disagree on the value of what the policy is about to do: a signal for safe
exploration (fall back to a safe action), for monitoring a deployed policy, or for active learning (collect data
there). After a short training it is typically larger on the states never seen than on the visited ones.
"""

import argparse

import gymnasium as gym
import numpy as np

from sb3_soup import SOUP


def visited_states(model: SOUP, n_states: int, seed: int) -> np.ndarray:
    """:return: ``(n_states, 3)`` observations met by the deterministic policy on Pendulum-v1"""
    env = gym.make("Pendulum-v1")
    obs, _ = env.reset(seed=seed)
    states = []
    for _ in range(n_states * 20):
        action, _ = model.predict(obs, deterministic=True)
        obs, _, terminated, truncated, _ = env.step(action)
        states.append(obs)
        if terminated or truncated:
            obs, _ = env.reset()
    return np.stack(states[::20])


def unseen_states(n_states: int) -> np.ndarray:
    """:return: ``(n_states, 3)`` pendulum states spinning at 12 to 20 rad/s, beyond Pendulum's limit of 8"""
    angles = np.linspace(-np.pi, np.pi, n_states, endpoint=False)
    speeds = np.linspace(12.0, 20.0, n_states)
    return np.stack([np.cos(angles), np.sin(angles), speeds], axis=1).astype(np.float32)


def report(title: str, model: SOUP, states: np.ndarray) -> float:
    """Print the ensemble's view of ``states``; :return: the mean ``q_spread``"""
    view = model.policy.ensemble_view(states)  # NumPy arrays, batch first
    print(f"\n{title}")
    print("  cos(theta) sin(theta) theta_dot |  action  head  Q mean  Q spread  candidates' spread")
    for state, action, head, q_mean, q_spread, candidates in zip(
        states, view.actions, view.chosen, view.q_mean, view.q_spread, view.candidates
    ):
        print(
            f"  {state[0]:10.2f} {state[1]:10.2f} {state[2]:9.2f} | {action[0]:7.2f} {head:5d} {q_mean:7.1f} "
            f"{q_spread:9.2f} {candidates[:, 0].std():19.2f}"
        )
    return float(view.q_spread.mean())


def main(timesteps: int = 5000, n_heads: int = 5, n_states: int = 5, seed: int = 0) -> tuple[float, float]:
    """
    :return: the mean ``q_spread`` of the visited and of the unseen states
    """
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=n_heads, learning_starts=min(1000, timesteps // 2), seed=seed)
    model.learn(timesteps)
    seen = report("States the policy visits:", model, visited_states(model, n_states, seed))
    unseen = report("States it never saw (spinning faster than Pendulum allows):", model, unseen_states(n_states))
    print(f"\nmean Q spread: visited {seen:.2f}, never seen {unseen:.2f}")
    return seen, unseen


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument("--timesteps", type=int, default=5000)
    parser.add_argument("--n-heads", type=int, default=5)
    parser.add_argument("--n-states", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(args.timesteps, args.n_heads, args.n_states, args.seed)
