"""The self-adaptive confidence (eq. 8): confidence in (0, 1], REINFORCE moves it towards rewarded critic heads."""

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_soup import SOUP, AdaptiveConfidence, ConfidenceStep, ConfidenceStrategy


def _strategy(n_heads: int = 2, **kwargs) -> AdaptiveConfidence:
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=n_heads, confidence=AdaptiveConfidence(**kwargs), seed=0)
    return model.policy.confidence  # type: ignore[return-value]


def _feed(strategy: ConfidenceStrategy, obs, q_matrix, chosen, rewards) -> dict:
    """What SOUP does around a training round: the strategy observes a step, then updates."""
    strategy.observe(ConfidenceStep(obs, q_matrix, chosen, rewards))
    return strategy.update()


def test_confidence_stays_in_the_unit_interval():
    strategy = _strategy(n_heads=4, eps=1e-3)
    obs = th.as_tensor(np.random.default_rng(0).normal(scale=100.0, size=(256, 3)), dtype=th.float32)
    confidence = strategy.confidence(obs)
    assert confidence.shape == (256, 4)
    assert bool((confidence >= 1e-3).all()) and bool((confidence <= 1.0).all())


@pytest.mark.parametrize("baseline", [True, False])
def test_reinforce_raises_the_confidence_of_the_rewarded_critic_head(baseline):
    """
    Toy problem: critic head 0 always prefers candidate 0, critic head 1 candidate 1, and only candidate 0 is
    rewarded. The selection that followed head 0 was the good one, so head 0's confidence must rise relative to head 1's.
    """
    th.manual_seed(0)
    strategy = _strategy(n_heads=2, lr=1e-2, baseline=baseline)
    rng = np.random.default_rng(0)
    obs = th.as_tensor(rng.normal(size=(64, 3)), dtype=th.float32)
    q_matrix = th.tensor([[1.0, 0.0], [0.0, 1.0]]).expand(64, 2, 2)  # V[i, k]: head i likes candidate i
    before = strategy.confidence(obs).mean(0).detach()
    for _ in range(100):
        chosen = th.as_tensor(rng.integers(0, 2, size=64))
        rewards = th.where(chosen == 0, 1.0, -1.0)
        _feed(strategy, obs, q_matrix, chosen, rewards)
    after = strategy.confidence(obs).mean(0).detach()
    assert after[0] - after[1] > before[0] - before[1] + 0.2
    assert after[0] > before[0] and after[1] < before[1]


def test_reinforce_with_positive_rewards_needs_the_baseline_to_tell_heads_apart():
    """All rewards positive: with the running-mean baseline the better head still wins."""
    th.manual_seed(0)
    strategy = _strategy(n_heads=2, lr=1e-2, baseline=True)
    rng = np.random.default_rng(1)
    obs = th.as_tensor(rng.normal(size=(64, 3)), dtype=th.float32)
    q_matrix = th.tensor([[1.0, 0.0], [0.0, 1.0]]).expand(64, 2, 2)
    for _ in range(100):
        chosen = th.as_tensor(rng.integers(0, 2, size=64))
        _feed(strategy, obs, q_matrix, chosen, th.where(chosen == 0, 11.0, 9.0))
    confidence = strategy.confidence(obs).mean(0)
    assert confidence[0] > confidence[1] + 0.2
    assert float(strategy.reward_baseline) == pytest.approx(10.0, abs=0.5)


def test_learning_hands_the_strategy_each_step_of_all_envs_and_updates_it_after_each_round():
    observed, updates = [], []

    class Recording(AdaptiveConfidence):
        def observe(self, step):
            observed.append(step)
            super().observe(step)

        def update(self):
            updates.append(len(self._rollout))
            return super().update()

    env = make_vec_env("Pendulum-v1", n_envs=2, seed=0)
    model = SOUP("MlpPolicy", env, n_heads=3, confidence=Recording(), learning_starts=10, batch_size=8, seed=0)
    model.learn(40)
    assert len(observed) == 20  # every vectorised step, warm-up included
    warm_up, selected = observed[:5], observed[5:]
    assert all(step.q_matrix is None and step.observations is None and step.rewards.shape == (2,) for step in warm_up)
    for step in selected:
        assert step.q_matrix.shape == (2, 3, 3) and step.observations.shape == (2, 3)
        assert step.chosen.shape == (2,) == step.rewards.shape
    assert updates and all(n == 1 for n in updates)  # one round per step (train_freq=1): each update sees one step
    assert "train/confidence_loss" in model.logger.name_to_value


def test_the_adaptive_rollout_is_bounded_when_no_round_comes():
    strategy = _strategy(n_heads=2)
    strategy.max_rollout = 3
    for _ in range(5):
        strategy.observe(ConfidenceStep(th.zeros(1, 3), th.zeros(1, 2, 2), th.zeros(1, dtype=th.long), th.zeros(1)))
    assert len(strategy._rollout) == 3


def test_a_custom_strategy_is_used_and_saved(tmp_path):
    class PreferFirstHead(ConfidenceStrategy):
        def weights(self, obs, q_matrix):
            weights = th.zeros(1, self.n_critic_heads, self.n_actor_heads)
            weights[:, 0] = 1.0
            return weights

    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, confidence=PreferFirstHead(), learning_starts=10, batch_size=8)
    model.learn(30)
    obs = th.zeros(4, 3)
    selection = model.policy.select(obs)
    assert th.equal(selection.chosen, selection.q_matrix[:, 0].argmax(1))
    model.save(tmp_path / "custom")
    loaded = SOUP.load(tmp_path / "custom")
    assert type(loaded.policy.confidence).__name__ == "PreferFirstHead"


def test_custom_strategy_with_a_wrong_shape_is_refused():
    class WrongShape(ConfidenceStrategy):
        def weights(self, obs, q_matrix):
            return th.ones(5, 7)

    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, confidence=WrongShape())
    with pytest.raises(ValueError, match=r"WrongShape.weights returned shape \(5, 7\)"):
        model.predict(np.zeros(3, dtype=np.float32))


def test_ucb_rates_candidates_by_mean_plus_lambda_std_while_exploring_and_by_the_mean_otherwise():
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, confidence="ucb", confidence_kwargs=dict(ucb_lambda=2.0), seed=0)
    strategy = model.policy.confidence
    q_matrix = th.as_tensor(np.random.default_rng(0).normal(size=(8, 3, 3)), dtype=th.float32)  # (B, Kc, Ka)
    obs = th.zeros(8, 3)
    optimistic = (strategy.exploration_weights(obs, q_matrix) * q_matrix).sum(dim=1)
    mean, std = q_matrix.mean(dim=1), q_matrix.std(dim=1, unbiased=False)
    th.testing.assert_close(optimistic, mean + 2.0 * std)
    th.testing.assert_close((strategy.weights(obs, q_matrix) * q_matrix).sum(dim=1), mean)


def test_ucb_explores_towards_the_disputed_candidate_and_acts_greedily_on_the_mean():
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=2, confidence="ucb", confidence_kwargs=dict(ucb_lambda=10.0), seed=0)
    # candidate 0: both heads agree on 1.0; candidate 1: mean 0.5, spread 1.0
    q_matrix = th.tensor([[[1.0, 1.5], [1.0, -0.5]]])
    obs = th.zeros(1, 3)
    greedy = (model.policy.confidence.weights(obs, q_matrix) * q_matrix).sum(dim=1).argmax(dim=1)
    exploring = (model.policy.confidence.exploration_weights(obs, q_matrix) * q_matrix).sum(dim=1).argmax(dim=1)
    assert greedy.item() == 0 and exploring.item() == 1
    model.learn(30)  # acts with it, saves and loads with the model
    assert model.policy.select(th.zeros(4, 3), explore=True).actions.shape == (4, 1)


def test_lcb_rates_candidates_by_mean_minus_kappa_std_exploring_or_not():
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, confidence="lcb", confidence_kwargs=dict(kappa=2.0), seed=0)
    strategy = model.policy.confidence
    q_matrix = th.as_tensor(np.random.default_rng(0).normal(size=(8, 3, 3)), dtype=th.float32)  # (B, Kc, Ka)
    obs = th.zeros(8, 3)
    mean, std = q_matrix.mean(dim=1), q_matrix.std(dim=1, unbiased=False)
    for weights in (strategy.weights(obs, q_matrix), strategy.exploration_weights(obs, q_matrix)):
        th.testing.assert_close((weights * q_matrix).sum(dim=1), mean - 2.0 * std)


def test_lcb_prefers_the_candidate_the_critics_agree_on():
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=2, confidence="lcb", seed=0)
    # candidate 0: both heads agree on 1.0; candidate 1: mean 1.25 (the plain argmax's pick), spread 0.75
    q_matrix = th.tensor([[[1.0, 2.0], [1.0, 0.5]]])
    rated = (model.policy.confidence.weights(th.zeros(1, 3), q_matrix) * q_matrix).sum(dim=1)
    assert q_matrix.mean(dim=1).argmax(dim=1).item() == 1 and rated.argmax(dim=1).item() == 0
    model.learn(30)  # acts with it
    with pytest.raises(ValueError, match=r"kappa must be a float in \[0, inf\) \(LCBConfidence's weight of the penalty\)"):
        SOUP("MlpPolicy", "Pendulum-v1", confidence="lcb", confidence_kwargs=dict(kappa=-1.0))


def test_adaptive_confidence_logs_how_decided_its_selection_policy_is():
    strategy = _strategy(n_heads=3)
    rng = np.random.default_rng(0)
    logs = _feed(
        strategy,
        th.as_tensor(rng.normal(size=(32, 3)), dtype=th.float32),
        th.as_tensor(rng.normal(size=(32, 3, 3)), dtype=th.float32),
        th.as_tensor(rng.integers(0, 3, size=32)),
        th.as_tensor(rng.normal(size=32), dtype=th.float32),
    )
    assert 1 / 3 <= logs["selection_max_prob"] <= 1.0
    assert logs["selection_logit_spread"] > 0


def test_a_relative_temperature_makes_the_selection_policy_independent_of_the_scale_of_q():
    absolute, relative = _strategy(n_heads=3), _strategy(n_heads=3, temperature_mode="relative")
    e_q = th.tensor([[1.0, 2.0, 4.0]])
    th.testing.assert_close(relative.selection_logits(100.0 * e_q), relative.selection_logits(e_q))
    assert relative.selection_logits(e_q).std(unbiased=False) == pytest.approx(1.0)  # unit spread at temperature 1
    assert th.softmax(absolute.selection_logits(100.0 * e_q), dim=1).max() > 0.99  # saturated by the scale
    assert th.equal(relative.selection_logits(th.ones(1, 3)), th.zeros(1, 3))  # equal candidates: uniform
