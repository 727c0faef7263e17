"""
The training schemes on one minibatch (one gradient step of ``SOUP.train``): Algorithm 1's active pair, all pairs, all
critics; masked losses, per-head targets, pessimistic and smoothed targets, n-step discounts, delayed actor updates;
K = 1 is DDPG.
"""

import copy

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import Logger

from sb3_soup import SOUP, DecayingNormalActionNoise, paper_settings
from sb3_soup.buffers import BootstrappedReplayBufferSamples
from sb3_soup.presets import PAPER_UPDATE

BATCH = 16


def _model(**kwargs) -> SOUP:
    """The paper's update (Algorithm 1): what each test changes one setting of, unless it says otherwise."""
    kwargs = {"n_heads": 3, **PAPER_UPDATE, **kwargs}
    return SOUP("MlpPolicy", "Pendulum-v1", learning_starts=0, batch_size=BATCH, seed=0, **kwargs)


def _batch(
    n_masks: int, masks: np.ndarray | None = None, seed: int = 0, discounts: th.Tensor | None = None
) -> BootstrappedReplayBufferSamples:
    rng = np.random.default_rng(seed)

    def tensor(*shape):
        return th.as_tensor(rng.normal(size=shape), dtype=th.float32)

    if masks is None:
        masks = np.ones((BATCH, n_masks), dtype=bool)
    return BootstrappedReplayBufferSamples(
        observations=tensor(BATCH, 3),
        actions=tensor(BATCH, 1).clamp(-1, 1),
        next_observations=tensor(BATCH, 3),
        dones=th.as_tensor(rng.random((BATCH, 1)) < 0.2, dtype=th.float32),
        rewards=tensor(BATCH, 1),
        masks=th.as_tensor(masks),
        discounts=discounts,
    )


def _step(model: SOUP, data: BootstrappedReplayBufferSamples, pair: int = 0) -> tuple[list[float], list[float]]:
    """
    One gradient step of the model's scheme (``SOUP.train``) on ``data``, with ``pair`` as the episode's active head pair.

    :return: the critic loss and the actor loss it logged, each as a list of zero or one value
    """
    model._active_pairs = np.array([pair])
    model.replay_buffer.sample = lambda batch_size, env=None: data  # type: ignore[method-assign,union-attr]
    model.set_logger(Logger(folder=None, output_formats=[]))
    model.train(gradient_steps=1, batch_size=BATCH)
    logged = model.logger.name_to_value
    return tuple([logged[key]] if key in logged else [] for key in ("train/critic_loss", "train/actor_loss"))  # type: ignore[return-value]


def _snapshot(model: SOUP) -> dict[str, th.Tensor]:
    return {name: value.detach().clone() for name, value in model.policy.state_dict().items()}


def _changed_heads(before: dict[str, th.Tensor], after: dict[str, th.Tensor], prefix: str) -> list[int]:
    """Indices of the heads of ``prefix`` (e.g. 'actor.') whose parameters changed."""
    changed = set()
    for name, value in before.items():
        if name.startswith(prefix) and ".heads." in name:
            diff = (after[name] - value).abs().flatten(1).sum(1)  # (K,)
            changed |= {int(k) for k in th.nonzero(diff).flatten()}
    return sorted(changed)


def _body_changed(before: dict[str, th.Tensor], after: dict[str, th.Tensor], prefix: str) -> bool:
    return any(
        not th.equal(value, after[name])
        for name, value in before.items()
        if name.startswith(prefix) and ".heads." not in name and value.is_floating_point()
    )


def test_the_default_scheme_trains_every_pair_with_td3s_target_smoothing_and_delay():
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, learning_starts=0, batch_size=BATCH, seed=0)
    assert (model.train_heads, model.target_q, model.policy_delay) == ("all", "min_pair", 2)
    assert (model.target_policy_noise, model.target_noise_clip) == (0.2, 0.5)
    before = _snapshot(model)
    _step(model, _batch(3))  # update 1: every critic head, no actor
    after = _snapshot(model)
    assert _changed_heads(before, after, "critic.") == [0, 1, 2] and _changed_heads(before, after, "actor.") == []
    _step(model, _batch(3, seed=1))  # update 2: every actor head too, and the targets
    final = _snapshot(model)
    for prefix in ("actor.", "actor_target.", "critic_target."):
        assert _changed_heads(after, final, prefix) == [0, 1, 2], prefix


def test_active_pair_step_changes_that_head_and_the_bodies_only():
    model = _model()
    before = _snapshot(model)
    _step(model, _batch(3), pair=1)
    after = _snapshot(model)
    for prefix in ("actor.", "critic.", "actor_target.", "critic_target."):
        assert _changed_heads(before, after, prefix) == [1], prefix
        assert _body_changed(before, after, prefix), prefix
    # the confidence network is trained by REINFORCE elsewhere, never by the DDPG losses
    assert not _body_changed(before, after, "confidence.")


def test_other_heads_stay_untouched_over_many_steps_of_one_head():
    """Adam's momentum must not move a head that is not trained (per-head optimizer state)."""
    model = _model()
    for _ in range(3):
        _step(model, _batch(3), pair=0)
    before = _snapshot(model)
    for seed in range(3):
        _step(model, _batch(3, seed=seed), pair=2)
    assert _changed_heads(before, _snapshot(model), "actor.") == [2]
    assert _changed_heads(before, _snapshot(model), "critic.") == [2]


@pytest.mark.parametrize("train_heads", ["active", "all"])
def test_masked_out_transitions_give_no_gradient(train_heads):
    """
    Changing the data of transitions whose mask is 0 for head k leaves head k's update unchanged.
    With every head trained at once, the actor heads are judged by critic heads on a shared critic body that the
    other heads' losses just moved, so the claim is about the critic heads there (the critic step comes first).
    """
    masks = np.ones((BATCH, 3), dtype=bool)
    masks[:5, 1] = False  # head 1 does not see the first five transitions
    batch = _batch(3, masks)
    perturbed = batch._replace(rewards=batch.rewards.clone(), actions=batch.actions.clone())
    perturbed.rewards[:5] += 100.0
    perturbed.actions[:5] = -perturbed.actions[:5]

    results = []
    for data in (batch, perturbed):
        model = _model(train_heads=train_heads)
        _step(model, data, pair=1)
        results.append(_snapshot(model))
    checked = ("actor.heads", "critic.heads") if train_heads == "active" else ("critic.heads",)
    for name, value in results[0].items():
        if name.startswith(checked):
            assert th.allclose(value[1], results[1][name][1], atol=1e-6), name  # head 1: same update
    if train_heads == "all":  # head 0 saw the change
        assert not th.allclose(results[0]["critic.heads.layers.0.weight"][0], results[1]["critic.heads.layers.0.weight"][0])


def test_all_zero_masks_mean_no_update_and_no_nan():
    model = _model()
    before = _snapshot(model)
    masks = np.ones((BATCH, 3), dtype=bool)
    masks[:, 2] = False
    assert _step(model, _batch(3, masks), pair=2) == ([], [])
    after = _snapshot(model)
    assert all(th.equal(value, after[name]) for name, value in before.items())

    model = _model(train_heads="all")
    before = _snapshot(model)
    (critic_loss,), (actor_loss,) = _step(model, _batch(3, masks))
    after = _snapshot(model)
    assert np.isfinite(critic_loss) and np.isfinite(actor_loss)
    assert _changed_heads(before, after, "critic.") == [0, 1]  # head 2 saw nothing: no update
    assert _changed_heads(before, after, "actor.") == [0, 1]


def test_all_heads_step_updates_every_head():
    model = _model(train_heads="all")
    before = _snapshot(model)
    _step(model, _batch(3))
    after = _snapshot(model)
    assert _changed_heads(before, after, "actor.") == [0, 1, 2]
    assert _changed_heads(before, after, "critic.") == [0, 1, 2]


def test_all_critics_step_updates_every_critic_head_and_the_active_actor_head():
    model = _model(train_heads="all_critics")
    before = _snapshot(model)
    _step(model, _batch(3), pair=2)
    after = _snapshot(model)
    assert _changed_heads(before, after, "critic.") == [0, 1, 2]
    assert _changed_heads(before, after, "critic_target.") == [0, 1, 2]
    assert _changed_heads(before, after, "actor.") == [2]
    assert _changed_heads(before, after, "actor_target.") == [2]


def test_policy_delay_updates_the_actor_and_the_targets_every_nth_critic_update():
    model = _model(train_heads="all", policy_delay=2)
    before = _snapshot(model)
    critic_loss, actor_loss = _step(model, _batch(3))  # update 1: the critic alone
    after = _snapshot(model)
    assert len(critic_loss) == 1 and actor_loss == []
    assert _changed_heads(before, after, "critic.") == [0, 1, 2]
    assert all(th.equal(value, after[name]) for name, value in before.items() if not name.startswith("critic."))
    critic_loss, actor_loss = _step(model, _batch(3, seed=1))  # update 2: critic, actor, targets
    final = _snapshot(model)
    assert len(critic_loss) == 1 and len(actor_loss) == 1
    for prefix in ("actor.", "actor_target.", "critic_target."):
        assert _changed_heads(after, final, prefix) == [0, 1, 2], prefix


def _critic_losses(
    model: SOUP, data: BootstrappedReplayBufferSamples, pair: int, discount: float | None = None
) -> list[float]:
    """
    Eqs. 3-4 by hand for head pair ``pair`` (masks all ones): element i is the critic loss with the target
    ``r + gamma (1 - done) min(Q'_pair, Q'_i)(s', mu'_pair(s'))``, so element ``pair`` is the paper's own target.
    """
    discount = model.gamma if discount is None else discount
    with th.no_grad():
        next_actions = model.actor_target(data.next_observations, pair)  # (B, A)
        own = model.critic_target(data.next_observations, next_actions, pair)  # (B, 1)
        current_q = model.critic(data.observations, data.actions, pair)  # (B, 1)
        losses = []
        for i in range(model.n_critic_heads):
            next_q = th.minimum(own, model.critic_target(data.next_observations, next_actions, i))
            target_q = data.rewards + discount * (1 - data.dones) * next_q
            losses.append(float(((target_q - current_q) ** 2).mean()))
    return losses


@pytest.mark.parametrize("pair", [0, 1, 2])
def test_own_target_is_the_pairs_own_target_heads(pair):
    data = _batch(3)
    expected = _critic_losses(_model(), data, pair)[pair]
    (loss,), _ = _step(_model(), data, pair=pair)
    assert loss == pytest.approx(expected, rel=1e-5)


def test_n_step_discounts_replace_gamma_in_the_target():
    """SB3's n-step buffers give each transition its discount (gamma ** n, or less where the episode ended)."""
    discounts = th.full((BATCH, 1), 0.99**3)
    discounts[:4] = 0.5
    data = _batch(3, discounts=discounts)
    (loss,), _ = _step(_model(), data, pair=1)
    with th.no_grad():
        model = _model()
        next_q = model.critic_target(data.next_observations, model.actor_target(data.next_observations, 1), 1)
        target_q = data.rewards + discounts * (1 - data.dones) * next_q
        expected = float(((target_q - model.critic(data.observations, data.actions, 1)) ** 2).mean())
    assert loss == pytest.approx(expected, rel=1e-5)
    assert loss != pytest.approx(_critic_losses(_model(), data, 1)[1], rel=1e-3)  # not gamma's


@pytest.mark.parametrize("pair", [0, 1, 2])
def test_min_pair_target_is_the_smaller_of_the_own_and_another_target_head(pair):
    data = _batch(3)
    candidates = _critic_losses(_model(), data, pair)
    others = [loss for i, loss in enumerate(candidates) if i != pair]
    drawn = set()
    for draw in range(8):  # the other head is drawn at random per pair and minibatch
        model = _model(target_q="min_pair")  # seeded: the draw's seed comes after
        th.manual_seed(draw)
        (loss,), _ = _step(model, data, pair=pair)
        drawn |= {i for i, other in enumerate(others) if loss == pytest.approx(other, rel=1e-5)}
        assert any(loss == pytest.approx(other, rel=1e-5) for other in others), (loss, candidates)
    assert drawn == {0, 1}  # either other head
    # with one critic head there is nothing to take the minimum with: the own target
    (one_head,), _ = _step(_model(n_heads=1, preset="ddpg", target_q="min_pair"), _batch(1))
    (own,), _ = _step(_model(n_heads=1, preset="ddpg"), _batch(1))
    assert one_head == own


def _redq_losses(model: SOUP, data: BootstrappedReplayBufferSamples, pair: int) -> dict[tuple[int, int], float]:
    """Eqs. 3-4 by hand for head pair ``pair``: the critic loss with the target ``r + gamma (1 - done) min(Q'_i, Q'_j)(s',
    mu'_pair(s'))`` for every two target heads i < j."""
    with th.no_grad():
        next_actions = model.actor_target(data.next_observations, pair)  # (B, A)
        next_q = [model.critic_target(data.next_observations, next_actions, i) for i in range(model.n_critic_heads)]
        current_q = model.critic(data.observations, data.actions, pair)  # (B, 1)
        losses = {}
        for i in range(model.n_critic_heads):
            for j in range(i + 1, model.n_critic_heads):
                target_q = data.rewards + model.gamma * (1 - data.dones) * th.minimum(next_q[i], next_q[j])
                losses[(i, j)] = float(((target_q - current_q) ** 2).mean())
    return losses


def test_redq_target_is_the_smaller_of_two_random_target_heads_the_same_for_every_pair():
    data = _batch(3)
    drawn = set()
    for draw in range(8):  # two heads drawn at random per minibatch, the pair's own among them or not
        model = _model(target_q="redq")  # seeded: the draw's seed comes after
        th.manual_seed(draw)
        (loss,), _ = _step(model, data, pair=0)
        matches = [
            heads for heads, expected in _redq_losses(_model(), data, 0).items() if loss == pytest.approx(expected, rel=1e-5)
        ]
        assert len(matches) == 1, (loss, matches)
        drawn |= set(matches)
    assert (1, 2) in drawn and len(drawn) > 1  # unlike min_pair, the own head need not be one of them
    # train_heads="all": every pair's target from the same two heads (the logged loss is the pairs' mean)
    (loss,), _ = _step(_model(target_q="redq", train_heads="all"), data)
    per_pair = [_redq_losses(_model(), data, pair) for pair in range(3)]
    means = {heads: np.mean([losses[heads] for losses in per_pair]) for heads in per_pair[0]}
    assert sum(loss == pytest.approx(mean, rel=1e-5) for mean in means.values()) == 1, (loss, means)
    # with one critic head: the own target
    (one_head,), _ = _step(_model(n_heads=1, preset="ddpg", target_q="redq"), _batch(1))
    (own,), _ = _step(_model(n_heads=1, preset="ddpg"), _batch(1))
    assert one_head == own


def test_target_policy_smoothing_adds_clipped_noise_to_the_target_actions():
    data = _batch(3)
    (plain,), _ = _step(_model(), data, pair=1)
    (clipped_to_zero,), _ = _step(_model(target_policy_noise=10.0, target_noise_clip=0.0), data, pair=1)
    assert clipped_to_zero == plain
    (smoothed,), _ = _step(_model(target_policy_noise=0.2), data, pair=1)
    assert smoothed != pytest.approx(plain, rel=1e-6)


def test_one_head_is_ddpg():
    """
    K = 1: the update is the DDPG update of eqs. 3-6 with plain Adam. Both sides use Adam eps=1e-4: with the default
    1e-8, gradients of 1e-11 (dead LeakyReLU slopes) turn float rounding differences into visible steps.
    """
    model = _model(
        n_heads=1,
        preset="ddpg",
        tau=0.1,
        gamma=0.9,
        learning_rate=1e-3,
        critic_learning_rate=2e-3,
        policy_kwargs=dict(optimizer_kwargs=dict(eps=1e-4)),
    )
    actor, critic = copy.deepcopy(model.actor), copy.deepcopy(model.critic)
    actor_target, critic_target = copy.deepcopy(model.actor_target), copy.deepcopy(model.critic_target)
    actor_opt = th.optim.Adam(actor.parameters(), lr=1e-3, eps=1e-4)
    critic_opt = th.optim.Adam(critic.parameters(), lr=2e-3, eps=1e-4)
    data = _batch(1)

    for _ in range(3):
        _step(model, data, pair=0)
        # eqs. 3-4
        with th.no_grad():
            y = data.rewards + 0.9 * (1 - data.dones) * critic_target(
                data.next_observations, actor_target(data.next_observations, 0), 0
            )
        critic_loss = ((y - critic(data.observations, data.actions, 0)) ** 2).mean()
        critic_opt.zero_grad()
        critic_loss.backward()
        critic_opt.step()
        # eq. 5
        actor_loss = -critic(data.observations, actor(data.observations, 0), 0).mean()
        actor_opt.zero_grad()
        actor_loss.backward()
        actor_opt.step()
        # eq. 6
        with th.no_grad():
            for net, target in ((actor, actor_target), (critic, critic_target)):
                for param, target_param in zip(net.parameters(), target.parameters()):
                    target_param.mul_(0.9).add_(0.1 * param)

    for mine, reference in ((model.actor, actor), (model.critic, critic), (model.actor_target, actor_target)):
        for param, ref_param in zip(mine.parameters(), reference.parameters()):
            assert th.allclose(param, ref_param, atol=1e-5)
    # DDPG acts with its single actor head, no critic in the loop
    obs = th.zeros(2, 3)
    assert model.policy.select(obs).q_matrix is None


def test_learning_rates_are_sb3s_by_default_and_the_papers_with_paper_settings():
    model = _model()
    assert model.actor.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3)
    assert model.critic.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3)
    env = gym.make("Pendulum-v1")
    paper = SOUP("MlpPolicy", env, n_heads=2, **paper_settings(env.action_space))
    assert paper.actor.optimizer.param_groups[0]["lr"] == pytest.approx(1e-4)
    assert paper.critic.optimizer.param_groups[0]["lr"] == pytest.approx(3e-4)
    assert (paper.batch_size, paper.tau) == (1024, 1e-3)
    # the paper's update (Algorithm 1), which is no longer the defaults' (every pair, TD3's target, smoothing and delay)
    assert (paper.train_heads, paper.target_q, paper.policy_delay, paper.target_policy_noise) == ("active", "own", 1, 0.0)
    noise = paper.action_noise  # the paper mode's decaying noise
    assert isinstance(noise, DecayingNormalActionNoise) and (noise.decay, noise.sigma_min) == (0.999995, 0.05)
    np.testing.assert_array_equal(noise.sigma, [0.2])
    # its confidence network's lr and temperature mode are the adaptive strategy's defaults
    assert (paper.policy.confidence.lr, paper.policy.confidence.temperature_mode) == (1e-4, "absolute")


def test_critic_learning_rate_schedule_is_applied():
    model = SOUP(
        "MlpPolicy", "Pendulum-v1", n_heads=2, learning_starts=20, batch_size=8, critic_learning_rate=lambda p: 1e-4 + p * 1e-3
    )
    model.learn(60)
    lr = model.critic.optimizer.param_groups[0]["lr"]
    assert 1e-4 <= lr < 1.1e-3
    assert model.logger.name_to_value["train/critic_learning_rate"] == pytest.approx(lr)
