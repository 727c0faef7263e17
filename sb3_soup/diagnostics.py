"""
What SOUP watches while it learns: the ensemble's statistics for the logs (which actor head's candidate is executed,
each critic head's confidence in its own candidate, the critic heads' disagreement) and the non-finite values that
stop training with an error naming the heads at fault (``check_finite``).
"""

from collections.abc import Callable

import numpy as np
import torch as th
from stable_baselines3.common.logger import Logger

from sb3_soup.policies import Selection


class EnsembleStats:
    """
    The ensemble's statistics since the last log dump, per selection (one per env and step):

    - ``selection/head_k``: how often actor head k's candidate was executed;
    - ``confidence/head_i``: mean weight of critic head i on its own candidate (candidate i, or the only one);
    - ``rollout/q_spread``: mean std over critic heads of the executed candidate's Q value.

    :param n_actor_heads: the actor's heads
    :param n_critic_heads: the critic's heads
    """

    def __init__(self, n_actor_heads: int, n_critic_heads: int):
        self.n_actor_heads = n_actor_heads
        self.n_critic_heads = n_critic_heads
        self.reset()

    def reset(self) -> None:
        """Start counting afresh."""
        self.selection_counts = np.zeros(self.n_actor_heads, dtype=np.int64)
        self.confidence_sum = np.zeros(self.n_critic_heads)
        self.q_spread_sum = 0.0
        self.n_selections = 0

    def record(self, selection: Selection) -> None:
        """:param selection: what the ensemble decided for a batch of observations"""
        self.selection_counts += np.bincount(selection.chosen.cpu().numpy(), minlength=self.n_actor_heads)
        self.n_selections += len(selection.chosen)
        if selection.q_matrix is None or selection.weights is None:
            return
        q_matrix = selection.q_matrix  # (B, Kc, Ka)
        weights = selection.weights.expand_as(q_matrix)
        heads = th.arange(self.n_critic_heads, device=q_matrix.device)
        own = weights[:, heads, heads.clamp(max=self.n_actor_heads - 1)]  # (B, Kc)
        self.confidence_sum += own.sum(dim=0).cpu().numpy()
        if self.n_critic_heads > 1:
            chosen_q = q_matrix.gather(2, selection.chosen.view(-1, 1, 1).expand(-1, self.n_critic_heads, 1))  # (B, Kc, 1)
            self.q_spread_sum += float(chosen_q.std(dim=1).sum())

    def dump(self, logger: Logger) -> None:
        """Record the means since the last dump (nothing when no selection was made), then reset."""
        if self.n_selections > 0:
            for k, count in enumerate(self.selection_counts):
                logger.record(f"selection/head_{k}", count / self.n_selections)
            if self.n_actor_heads > 1 or self.n_critic_heads > 1:
                for i, total in enumerate(self.confidence_sum):
                    logger.record(f"confidence/head_{i}", total / self.n_selections)
            if self.n_critic_heads > 1:
                logger.record("rollout/q_spread", self.q_spread_sum / self.n_selections)
        self.reset()


def check_selection(selection: Selection, strategy_name: str, step: int) -> None:
    """
    Stop at the first non-finite E-action, Q value or confidence weight met while acting: one fused check on tensors
    already computed; the heads are only worked out once something is non-finite.

    :param selection: what the ensemble decided
    :param strategy_name: the confidence strategy's class name, for the message
    :param step: the env-step, for the message
    :raises FloatingPointError: naming the actor heads, critic heads or strategy at fault
    """
    finite = th.isfinite(selection.actions).all()
    if selection.q_matrix is not None and selection.weights is not None:
        finite = finite & th.isfinite(selection.q_matrix).all() & th.isfinite(selection.weights).all()
    if bool(finite):
        return
    problems = []
    if selection.q_matrix is not None:
        bad = ~th.isfinite(selection.q_matrix)  # (B, Kc, Ka)
        bad_candidates = bad.all(dim=1).any(dim=0)  # (Ka,): every critic head gave a non-finite Q to this candidate
        bad_critics = (bad & ~bad_candidates.view(1, 1, -1)).any(dim=2).any(dim=0)  # (Kc,): the other non-finite Qs
        if bool(bad_candidates.any()):
            heads = th.nonzero(bad_candidates).flatten().tolist()
            problems.append(f"every critic head gave a non-finite Q value to the candidate(s) of actor head(s) {heads}")
        if bool(bad_critics.any()):
            problems.append(f"critic head(s) {th.nonzero(bad_critics).flatten().tolist()} gave non-finite Q values")
    if selection.weights is not None and not bool(th.isfinite(selection.weights).all()):
        problems.append(f"the confidence strategy {strategy_name} gave non-finite weights")
    bad_envs = ~th.isfinite(selection.actions).all(dim=1)
    if bool(bad_envs.any()):
        heads = sorted(set(selection.chosen[bad_envs].tolist()))
        problems.append(f"actor head(s) {heads} proposed non-finite actions")
    raise FloatingPointError(
        f"non-finite values while acting at step {step}: {'; '.join(problems)}. Resume from an earlier "
        "checkpoint (with lower learning rates or a rescaled reward), or pass check_finite=False to act on anyway"
    )


def check_loss(name: str, value: float, where: Callable[[], str], update: int, step: int) -> None:
    """
    The one place where training stops on a non-finite loss: a ``math.isfinite`` on a loss already fetched for
    logging; ``where`` is only called once a value is non-finite.

    :param name: the loss ("critic_loss", "actor_loss", "confidence_loss")
    :param value: its value
    :param where: says what the loss trained (which head pairs, the confidence strategy)
    :param update: the gradient step, for the message
    :param step: the env-step, for the message
    :raises FloatingPointError: when ``value`` is NaN or inf
    """
    if np.isfinite(value):
        return
    raise FloatingPointError(
        f"non-finite {name} ({value}) for {where()} at update {update} (step {step}): the Q values or their targets "
        "diverged. This update was applied, so the model's parameters may be non-finite too: resume from an earlier "
        "checkpoint with lower learning rates or a rescaled reward, or pass check_finite=False to train on anyway"
    )
