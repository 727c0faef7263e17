"""Equation 7 (E-Critic, E-Actor) and the four confidence strategies, on hand-made Q matrices."""

import numpy as np
import pytest
import torch as th

from sb3_soup import (
    SOUP,
    AdaptiveConfidence,
    ConfidenceStep,
    ConfidenceStrategy,
    DecayedConfidence,
    FixedConfidence,
    NoConfidence,
)
from sb3_soup.policies import e_actor, e_critic

# V[i, k] = Q_i(s, a^k): critic head i scores candidate k (one observation, K = 3)
V = th.tensor([[[1.0, 5.0, 2.0], [4.0, 1.0, 2.0], [1.0, 1.0, 3.0]]])  # (1, 3, 3)
CANDIDATES = th.tensor([[[0.1]], [[0.2]], [[0.3]]])  # (Ka=3, B=1, A=1)


class _Heads:
    def __init__(self, n_critic: int, n_actor: int):
        self.n_critic_heads = n_critic
        self.n_actor_heads = n_actor


def _setup(strategy: ConfidenceStrategy, n_critic: int = 3, n_actor: int = 3) -> ConfidenceStrategy:
    strategy.setup(_Heads(n_critic, n_actor))  # type: ignore[arg-type]
    return strategy


def _select(weights: th.Tensor) -> int:
    actions, chosen = e_actor(CANDIDATES, e_critic(V, weights))
    assert th.equal(actions, CANDIDATES[chosen.item(), 0].unsqueeze(0))
    return int(chosen.item())


def test_e_critic_is_the_weighted_column_sum():
    weights = th.tensor([[[1.0, 2.0, 3.0], [0.5, 0.5, 0.5], [0.0, 1.0, 2.0]]])
    expected = th.tensor([[1 * 1 + 0.5 * 4 + 0 * 1, 2 * 5 + 0.5 * 1 + 1 * 1, 3 * 2 + 0.5 * 2 + 2 * 3]])
    assert th.allclose(e_critic(V, weights), expected)


def test_no_confidence_sums_the_heads():
    weights = _setup(NoConfidence()).weights(None, V)
    assert th.equal(weights.expand_as(V), th.ones_like(V))
    # column sums: [6, 7, 7] -> the first maximum, candidate 1
    assert th.allclose(e_critic(V, weights), th.tensor([[6.0, 7.0, 7.0]]))
    assert _select(weights) == 1


def test_fixed_confidence_matrix_and_choice():
    weights = _setup(FixedConfidence(alpha=0.8)).weights(None, V)
    expected = th.tensor([[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]])
    assert th.allclose(weights[0], expected)
    # v = [0.8 + 0.4 + 0.1, 0.5 + 0.8 + 0.1, 0.2 + 0.2 + 2.4] = [1.3, 1.4, 2.8]
    assert th.allclose(e_critic(V, weights), th.tensor([[1.3, 1.4, 2.8]]))
    assert _select(weights) == 2


def test_decayed_confidence_goes_from_identity_to_uniform():
    strategy = _setup(DecayedConfidence(decay=0.5))
    assert th.allclose(strategy.weights(None, V)[0], th.eye(3))  # d = 1: each head judges its own candidate
    assert _select(strategy.weights(None, V)) == 2  # diag(V) = [1, 1, 3]
    strategy.observe(ConfidenceStep(None, None, None, th.zeros(1)))  # one env-step: d = 0.5
    assert th.allclose(strategy.weights(None, V)[0], th.tensor([[0.5, 0.25, 0.25], [0.25, 0.5, 0.25], [0.25, 0.25, 0.5]]))
    strategy.observe(ConfidenceStep(None, None, None, th.zeros(10)))  # 10 envs: 0.5 ** 11 < 1/3, floored at 1/K (uniform)
    assert th.allclose(strategy.weights(None, V), th.full((1, 3, 3), 1 / 3))
    assert strategy.diagonal == pytest.approx(1 / 3)


def test_decayed_confidence_counts_every_env_step_warm_up_included():
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=5, confidence="decayed", learning_starts=1000, seed=0)
    strategy = model.policy.confidence
    assert isinstance(strategy, DecayedConfidence) and strategy.decay == 0.9995  # the paper's
    model.learn(400)  # random warm-up steps only
    assert strategy.diagonal == pytest.approx(0.9995**400)
    # the paper's decay reaches 1/K = 0.2 after 3,219 steps (README: before a 10k-step warm-up ends)
    strategy.n_steps.fill_(3218)
    assert strategy.diagonal > 0.2
    strategy.n_steps.fill_(3219)
    assert strategy.diagonal == 0.2


def test_adaptive_confidence_weights_each_critic_head_by_its_confidence():
    class HandMade(AdaptiveConfidence):
        def confidence(self, obs):
            return th.tensor([[0.1, 1.0, 0.2]])

    strategy = HandMade()
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, confidence=strategy, learning_starts=10)
    assert model.policy.confidence is strategy  # a user's strategy object is used as given
    weights = strategy.weights(None, V)
    assert weights.shape == (1, 3, 1)  # the same c_i for every candidate
    # v = 0.1 * V[0] + 1.0 * V[1] + 0.2 * V[2] = [4.3, 1.7, 2.8]
    assert th.allclose(e_critic(V, weights), th.tensor([[4.3, 1.7, 2.8]]))
    assert _select(weights) == 0


def test_one_critic_head_means_unit_weights():
    for strategy in (NoConfidence(), FixedConfidence(0.3), DecayedConfidence(0.9)):
        weights = _setup(strategy, n_critic=1, n_actor=3).weights(None, V[:, :1])
        assert th.equal(weights.expand(1, 1, 3), th.ones(1, 1, 3))


def test_a_policy_refuses_unpaired_head_counts():
    with pytest.raises(ValueError, match="actor head k is paired with critic head k"):
        SOUP("MlpPolicy", "Pendulum-v1", n_actor_heads=2, n_critic_heads=3)


def test_policy_select_matches_the_equation_on_its_own_networks():
    model = SOUP(
        "MlpPolicy",
        "Pendulum-v1",
        n_heads=4,
        confidence="fixed",
        confidence_kwargs=dict(alpha=0.7),
        seed=3,
        learning_starts=10,
    )
    obs = th.as_tensor(np.random.default_rng(0).normal(size=(6, 3)), dtype=th.float32)
    with th.no_grad():
        selection = model.policy.select(obs)
        candidates = model.actor(obs)  # (K, B, A)
        q = th.stack([th.stack([model.critic(obs, candidates[k], head=i)[:, 0] for k in range(4)], 1) for i in range(4)], 1)
    assert th.allclose(selection.q_matrix, q, atol=1e-5)  # V[b, i, k] = Q_i(s_b, a_b^k)
    eye = th.eye(4)
    weights = eye * 0.7 + (1 - eye) * 0.1
    chosen = (weights * q).sum(1).argmax(1)
    assert th.equal(selection.chosen, chosen)
    assert th.allclose(selection.actions, candidates[chosen, th.arange(6)])
    # predict() acts with the ensemble: the E-action rescaled to the bounds
    action, _ = model.predict(obs.numpy(), deterministic=True)
    assert np.allclose(action, 2.0 * candidates[chosen, th.arange(6)].numpy(), atol=1e-5)
