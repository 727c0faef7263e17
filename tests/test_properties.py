"""Property tests (hypothesis): the selection math for any V and W, and the bootstrap masks for any buffer."""

import numpy as np
import torch as th
from gymnasium import spaces
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from sb3_soup import (
    SOUP,
    BootstrappedDictReplayBuffer,
    BootstrappedReplayBuffer,
    ConfidenceStep,
    DecayedConfidence,
    FixedConfidence,
)
from sb3_soup.policies import e_actor, e_critic

# Deterministic on CI: the same examples every run, no deadline on a loaded machine
PROPERTIES = settings(max_examples=60, deadline=None, derandomize=True)

# Small integers and dyadic weights: every product and sum is exact in float32, so E-Q values compare exactly
Q_VALUES = st.integers(-40, 40).map(float)
WEIGHTS = st.sampled_from([0.0, 0.25, 0.5, 0.75, 1.0, 2.0])


@st.composite
def selection_problems(draw):
    """V (B, Kc, Ka), W broadcastable to it, candidates (Ka, B, A)."""
    batch, n_actor, action_dim = draw(st.integers(1, 4)), draw(st.integers(1, 6)), draw(st.integers(1, 3))
    n_critic = draw(st.sampled_from([1, n_actor]))  # paired heads, or one critic head
    q_matrix = draw(arrays(np.float32, (batch, n_critic, n_actor), elements=Q_VALUES))
    weight_shape = draw(st.sampled_from([(batch, n_critic, n_actor), (1, n_critic, n_actor), (batch, n_critic, 1)]))
    weights = draw(arrays(np.float32, weight_shape, elements=WEIGHTS))
    candidates = draw(arrays(np.float32, (n_actor, batch, action_dim), elements=st.floats(-1, 1, width=32)))
    return th.as_tensor(q_matrix), th.as_tensor(weights), th.as_tensor(candidates)


@PROPERTIES
@given(selection_problems())
def test_the_chosen_candidate_maximises_the_e_q_value(problem):
    q_matrix, weights, candidates = problem
    actions, chosen = e_actor(candidates, e_critic(q_matrix, weights))
    e_q = (np.broadcast_to(weights.numpy(), q_matrix.shape) * q_matrix.numpy()).sum(axis=1)  # eq. 7, by hand
    rows = np.arange(len(e_q))
    assert np.array_equal(e_q[rows, chosen.numpy()], e_q.max(axis=1))
    assert th.equal(actions, candidates[chosen, th.arange(candidates.shape[1])])


@PROPERTIES
@given(selection_problems(), st.randoms(use_true_random=False))
def test_permuting_the_heads_permutes_the_choice(problem, rng):
    """Relabel the head pairs (actor head k with critic head k): the same candidate wins, under its new label."""
    q_matrix, weights, candidates = problem
    n_critic, n_actor = q_matrix.shape[1:]
    perm = list(range(n_actor))
    rng.shuffle(perm)
    critic_perm = perm if n_critic == n_actor else [0]
    permuted_w = weights[:, critic_perm] if weights.shape[2] == 1 else weights[:, critic_perm][:, :, perm]
    e_q = e_critic(q_matrix, weights)
    e_q_permuted = e_critic(q_matrix[:, critic_perm][:, :, perm], permuted_w)
    assert th.equal(e_q_permuted, e_q[:, perm])  # candidate k's value moves to its new label
    actions, chosen = e_actor(candidates, e_q)
    actions_p, chosen_p = e_actor(candidates[perm], e_q_permuted)
    original_label = th.as_tensor(perm)[chosen_p]
    assert th.equal(e_q.gather(1, original_label.unsqueeze(1)), e_q.gather(1, chosen.unsqueeze(1)))  # a best one
    unique = (e_q == e_q.max(dim=1, keepdim=True).values).sum(dim=1) == 1
    assert th.equal(original_label[unique], chosen[unique]) and th.equal(actions_p[unique], actions[unique])


@PROPERTIES
@given(st.integers(2, 8), st.floats(0.01, 0.99), st.integers(0, 2000), st.permutations(range(8)))
def test_paired_strategies_treat_every_head_pair_alike(n_heads, alpha, n_steps, perm8):
    """Fixed and decayed weights do not depend on the heads' labels: W[perm][:, perm] == W."""
    perm = [k for k in perm8 if k < n_heads]
    heads = type("Heads", (), {"n_critic_heads": n_heads, "n_actor_heads": n_heads})()
    decayed = DecayedConfidence(decay=0.999)
    fixed = FixedConfidence(alpha=alpha)
    for strategy in (fixed, decayed):
        strategy.setup(heads)  # type: ignore[arg-type]
    decayed.observe(ConfidenceStep(None, None, None, th.zeros(n_steps)))
    for strategy in (fixed, decayed):
        weights = strategy.weights(None, th.zeros(1, n_heads, n_heads))
        assert th.equal(weights[:, perm][:, :, perm], weights)
        assert th.allclose(weights.sum(dim=1), th.ones(1, n_heads))  # each candidate's weights sum to 1


@settings(max_examples=8, deadline=None, derandomize=True)
@given(st.permutations(range(4)))
def test_permuting_the_networks_heads_permutes_the_policys_selection(perm):
    """The same property on real networks: relabel the heads' parameters (actor, critic, confidence network)."""
    model = SOUP(
        "MlpPolicy",
        "Pendulum-v1",
        n_heads=4,
        seed=0,
        policy_kwargs=dict(net_arch=dict(pi_body=[8], pi_head=[8], qf_body=[8, 8], qf_head=[8])),
    )
    obs = th.as_tensor(np.random.default_rng(0).normal(size=(32, 3)), dtype=th.float32)
    with th.no_grad():
        before = model.policy.select(obs)
        index = th.as_tensor(perm)
        for module in (model.actor.heads, model.critic.heads):
            for parameter in module.parameters():
                parameter.copy_(parameter[index])
        out = model.policy.confidence.network.out
        out.weight.copy_(out.weight[index])
        out.bias.copy_(out.bias[index])
        after = model.policy.select(obs)
    assert th.allclose(after.q_matrix, before.q_matrix[:, index][:, :, index], atol=1e-6)
    e_q = e_critic(before.q_matrix, before.weights)
    top2 = e_q.topk(2, dim=1).values
    clear = (top2[:, 0] - top2[:, 1]) > 1e-4  # no near-tie that rounding could flip
    assert clear.sum() > 20
    assert th.equal(index[after.chosen][clear], before.chosen[clear])
    assert th.allclose(after.actions[clear], before.actions[clear], atol=1e-6)


OBS = spaces.Box(-1, 1, (2,), np.float32)
DICT_OBS = spaces.Dict({"a": OBS})
ACT = spaces.Box(-1, 1, (1,), np.float32)


@PROPERTIES
@given(
    n_envs=st.integers(1, 4),
    buffer_size=st.integers(1, 300),
    n_masks=st.integers(1, 6),
    mask_prob=st.sampled_from([0.1, 0.3, 0.5, 0.9, 1.0]),
    n_adds=st.integers(1, 400),
    dict_obs=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_masks_keep_their_shape_and_rate_for_any_buffer(n_envs, buffer_size, n_masks, mask_prob, n_adds, dict_obs, seed):
    np.random.seed(seed)
    buffer_class = BootstrappedDictReplayBuffer if dict_obs else BootstrappedReplayBuffer
    buffer = buffer_class(
        buffer_size, DICT_OBS if dict_obs else OBS, ACT, device="cpu", n_envs=n_envs, n_masks=n_masks, mask_prob=mask_prob
    )
    rows = max(buffer_size // n_envs, 1)  # SB3 splits the size over the envs
    assert buffer.masks.shape == (rows, n_envs, n_masks) and buffer.masks.dtype == np.bool_
    for step in range(n_adds):
        obs = np.full((n_envs, 2), step, dtype=np.float32)
        obs_in = {"a": obs} if dict_obs else obs
        buffer.add(obs_in, obs_in, np.zeros((n_envs, 1)), np.zeros(n_envs), np.zeros(n_envs), [{}] * n_envs)
    stored = buffer.masks[: buffer.size()]
    assert buffer.size() == min(n_adds, rows) and stored.shape == (min(n_adds, rows), n_envs, n_masks)
    n = stored.size
    if mask_prob == 1.0:
        assert stored.all()
    else:  # Bernoulli(mask_prob) draws: within 5 standard deviations
        assert abs(stored.sum() - n * mask_prob) <= 5 * np.sqrt(n * mask_prob * (1 - mask_prob)) + 1
    samples = buffer.sample(16)
    assert samples.masks.shape == (16, n_masks) and samples.masks.dtype == th.bool
