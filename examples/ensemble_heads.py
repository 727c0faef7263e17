"""
Does the ensemble beat its members? Evaluate a saved SOUP model's E-action (what ``predict(deterministic=True)``
executes: the candidate the critic heads score best) against each actor head acting alone, on the same episodes.

    python examples/ensemble_heads.py runs/b200/HalfCheetah-v4/soup_defaults/seed_1/model.zip --env HalfCheetah-v4 \
        --episodes 3 --json heads.json

Each policy runs SB3's ``evaluate_policy`` on an env seeded alike, so all of them start from the same states. It prints
the mean return of the E-action and of each head, and how often each head's candidate was the one executed. Heads that
score what the E-action scores, with a small ``q_spread``, say the ensemble has become one policy; heads far below it
say the selection is doing the work.
"""

import argparse
import json

import numpy as np
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_soup import SOUP


class EnsemblePolicy:
    """A SOUP model as ``evaluate_policy`` runs it, acting with one actor head (``head``) or the E-action (None)."""

    def __init__(self, model: SOUP, head: int | None = None):
        self.model, self.head = model, head
        self.chosen = np.zeros(model.policy.n_actor_heads, dtype=np.int64)  # E-action: which head's candidate ran
        self.q_spreads: list[float] = []

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        view = self.model.policy.ensemble_view(observation)  # batched: (n_envs, ...) fields
        if self.head is not None:
            return view.candidates[:, self.head], state  # (n_envs, A)
        np.add.at(self.chosen, view.chosen, 1)
        self.q_spreads.extend(view.q_spread.tolist())
        return view.actions, state  # (n_envs, A): predict(observation, deterministic=True)[0]


def evaluate_heads(model: SOUP, env_id: str, n_episodes: int = 3, seed: int = 1000) -> dict:
    """
    :return: ``e_action`` and ``heads`` (one per actor head): mean and per-episode returns; ``chosen_fraction``: how
        often each head's candidate was executed by the E-action; ``q_spread``: the mean disagreement of the critic
        heads on the executed action
    """

    def returns(policy: EnsemblePolicy) -> list[float]:
        env = make_vec_env(env_id, n_envs=1, seed=seed)  # the same start states for every policy
        episode_returns, _ = evaluate_policy(policy, env, n_eval_episodes=n_episodes, return_episode_rewards=True)
        env.close()
        return [float(r) for r in episode_returns]

    e_policy = EnsemblePolicy(model)
    e_returns = returns(e_policy)
    heads = [returns(EnsemblePolicy(model, head)) for head in range(model.policy.n_actor_heads)]
    return {
        "env_id": env_id,
        "episodes": n_episodes,
        "e_action": {"mean": float(np.mean(e_returns)), "returns": e_returns},
        "heads": [{"mean": float(np.mean(r)), "returns": r} for r in heads],
        "chosen_fraction": (e_policy.chosen / e_policy.chosen.sum()).tolist(),
        "q_spread": float(np.mean(e_policy.q_spreads)),
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", help="a saved SOUP model (.zip)")
    parser.add_argument("--env", required=True, help="the Gymnasium env id it was trained on, e.g. HalfCheetah-v4")
    parser.add_argument("--episodes", type=int, default=3, help="evaluation episodes per policy")
    parser.add_argument("--seed", type=int, default=1000, help="seed of the evaluation env")
    parser.add_argument("--json", help="also write the results to this file")
    args = parser.parse_args(argv)
    result = evaluate_heads(SOUP.load(args.model, device="cpu"), args.env, args.episodes, args.seed)
    result["model"] = args.model
    print(f"E-action: {result['e_action']['mean']:.1f}  (q_spread {result['q_spread']:.3f})")
    for k, (head, fraction) in enumerate(zip(result["heads"], result["chosen_fraction"])):
        print(f"head {k}:   {head['mean']:.1f}  (its candidate executed on {100 * fraction:.0f}% of the E-action's steps)")
    if args.json:
        with open(args.json, "w") as file:
            json.dump(result, file, indent=1)
    return result


if __name__ == "__main__":
    main()
