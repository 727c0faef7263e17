"""
The paper's DDPG equations (3-5) for a stack of H head pairs trained on one minibatch, each on the transitions its
bootstrap mask keeps. Every training scheme of :class:`sb3_soup.SOUP` (the paper's active pair, all pairs, ...) is a
choice of which heads go into these functions and which target values they get; the equations are written once here.

Shapes: H head pairs being trained, B transitions in the minibatch.
"""

import torch as th


def masked_mean(values: th.Tensor, masks: th.Tensor) -> th.Tensor:
    """
    Mean of each head's values over the transitions its bootstrap mask keeps (Algorithm 1: "the i-th experience with
    mask m_i^k = 0 is ignored"); 0 for a head whose mask keeps none.

    :param values: ``(H, B, 1)``
    :param masks: ``(H, B, 1)``, 1.0 where head h sees transition b
    :return: ``(H,)``
    """
    return ((masks * values).sum(dim=1) / masks.sum(dim=1).clamp(min=1)).squeeze(-1)


def td_target(rewards: th.Tensor, dones: th.Tensor, discounts: float | th.Tensor, next_q: th.Tensor) -> th.Tensor:
    """
    Eq. 4: ``y = r + gamma * (1 - done) * Q'(s', mu'(s'))``, per head; with n-step returns (SB3's ``NStepReplayBuffer``),
    ``r`` is the discounted sum of the n rewards and ``discounts`` the ``gamma ** n`` of each sample (fewer steps where
    its episode ended sooner), as in SB3's TD3: ``y = r + (1 - done) * discount * Q'``.

    :param rewards: ``(B, 1)``
    :param dones: ``(B, 1)``, 1.0 where the episode terminated (timeouts are not terminations, see SB3)
    :param discounts: the discount factor gamma, or ``(B, 1)``, each sample's (n-step returns)
    :param next_q: ``(H, B, 1)``, each head's value of the next state (see :meth:`sb3_soup.SOUP._next_q`)
    :return: ``(H, B, 1)``
    """
    return rewards + (1 - dones) * discounts * next_q


def critic_loss(current_q: th.Tensor, target_q: th.Tensor, masks: th.Tensor) -> th.Tensor:
    """
    Eq. 3, masked: ``sum_j m_j (y_j - Q(s_j, a_j))^2 / sum_j m_j`` for each head.

    :param current_q: ``(H, B, 1)``, ``Q_h(s, a)`` of the stored actions
    :param target_q: ``(H, B, 1)``, from :func:`td_target`
    :param masks: ``(H, B, 1)``
    :return: ``(H,)``
    """
    return masked_mean((target_q - current_q) ** 2, masks)


def actor_loss(q_pi: th.Tensor, masks: th.Tensor) -> th.Tensor:
    """
    Eq. 5 as a loss: ``-mean_j Q(s_j, mu(s_j))`` over the kept transitions, for each head (its gradient is the
    deterministic policy gradient).

    :param q_pi: ``(H, B, 1)``, each critic head's value of its actor head's action
    :param masks: ``(H, B, 1)``
    :return: ``(H,)``
    """
    return -masked_mean(q_pi, masks)
