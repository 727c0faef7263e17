"""
Confidence strategies (Section 5.2 of the paper): the weight matrix ``W`` of the E-Critic layer.

The E-Q value of candidate k is ``v[k] = sum_i W[i, k] * V[i, k]`` where ``V[i, k] = Q_i(s, a^k)``
(critic head i scores candidate k). A strategy is an ``nn.Module`` so that its parameters and state
(a decay counter, a reward baseline) are saved, loaded and moved to the device with the policy.

Write your own by subclassing :class:`ConfidenceStrategy` and implementing :meth:`ConfidenceStrategy.weights`.
"""

import inspect
import math
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, NamedTuple

import torch as th
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn
from torch.nn import functional as F

from sb3_soup.networks import mlp
from sb3_soup.validation import boolean, choice, given, integer, number

if TYPE_CHECKING:
    from sb3_soup.policies import SOUPPolicy

__all__ = [
    "CONFIDENCE_STRATEGIES",
    "STRATEGIES",
    "AdaptiveConfidence",
    "ConfidenceStep",
    "ConfidenceStrategy",
    "DecayedConfidence",
    "FixedConfidence",
    "LCBConfidence",
    "NoConfidence",
    "UCBConfidence",
    "make_confidence",
]


class ConfidenceStep(NamedTuple):
    """What happened at one vectorised environment step of ``learn``: SOUP hands it to the strategy, nothing more."""

    # The selection made, when the ensemble made one from a Q matrix (None during the random warm-up, and with one actor
    # and one critic head): the observations (n_envs, *obs_shape) as given to the policy, V (n_envs, Kc, Ka) and the
    # index of the executed candidate (n_envs,)
    observations: PyTorchObs | None
    q_matrix: th.Tensor | None
    chosen: th.Tensor | None
    rewards: th.Tensor  # (n_envs,) the rewards that followed


class ConfidenceStrategy(nn.Module, ABC):
    """
    Interface of a confidence strategy: the weights ``W`` of the E-Critic layer (eq. 7) and how they learn (eq. 8).

    - :meth:`weights` gives ``W`` (shape ``(B, Kc, Ka)``, or broadcastable to it) for a batch of observations;
    - :meth:`exploration_weights` gives the ``W`` used while exploring (``learn``, ``predict(deterministic=False)``),
      by default the same;
    - :meth:`observe` is told what happened at each vectorised environment step of ``learn``;
    - :meth:`update` is called after each training round, to learn from what it observed since; it returns values to log;
    - anything to save goes in parameters/buffers (saved with the policy) or :attr:`optimizer` (saved with the model).
    """

    optimizer: th.optim.Optimizer | None = None

    def __init__(self) -> None:
        super().__init__()
        self.n_critic_heads = 1
        self.n_actor_heads = 1

    def setup(self, policy: "SOUPPolicy") -> None:
        """Called by the policy once it knows its head counts (build networks and optimizers here)."""
        self.n_critic_heads = policy.n_critic_heads
        self.n_actor_heads = policy.n_actor_heads

    @abstractmethod
    def weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        """
        :param obs: preprocessed observation batch (as given to the policy)
        :param q_matrix: ``V`` of shape ``(B, Kc, Ka)``
        :return: ``W`` of shape ``(B, Kc, Ka)`` or broadcastable to it
        """

    def exploration_weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        """
        ``W`` while exploring (``learn``, ``predict(deterministic=False)``); by default :meth:`weights`.

        :param obs: preprocessed observation batch (as given to the policy)
        :param q_matrix: ``V`` of shape ``(B, Kc, Ka)``
        :return: ``W`` of shape ``(B, Kc, Ka)`` or broadcastable to it
        """
        return self.weights(obs, q_matrix)

    def observe(self, step: ConfidenceStep) -> None:
        """
        Called after every vectorised environment step of ``learn`` (warm-up included) with what happened.

        :param step: the observations, the selection made and the rewards that followed
        """

    def update(self) -> dict[str, float]:
        """Called after each training round: learn from what was observed since the last one; return values to log."""
        return {}


def _pairwise_weights(diagonal: th.Tensor, n_critic: int, n_actor: int) -> th.Tensor:
    """``diagonal`` on the diagonal, ``(1 - diagonal) / (K - 1)`` elsewhere; all ones when Kc or Ka is 1."""
    if n_critic == 1 or n_actor == 1:
        return th.ones(1, n_critic, n_actor, device=diagonal.device)
    eye = th.eye(n_critic, device=diagonal.device)
    return (eye * diagonal + (1 - eye) * (1 - diagonal) / (n_critic - 1)).unsqueeze(0)  # (1, K, K)


class NoConfidence(ConfidenceStrategy):
    """``W[i, k] = 1``: the plain sum of the critic heads (DBDDPG)."""

    def weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        return th.ones(1, self.n_critic_heads, self.n_actor_heads, device=q_matrix.device)


class FixedConfidence(ConfidenceStrategy):
    """
    ``W[i, k] = alpha`` if ``i == k`` else ``(1 - alpha) / (K - 1)``.

    :param alpha: confidence of a critic head in its own actor head's candidate, in (0, 1)
    """

    def __init__(self, alpha: float = 0.5):
        super().__init__()
        self.alpha = number(0.0, 1.0, True, True, "FixedConfidence's confidence of a head in its own candidate")(
            "alpha", alpha
        )

    def weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        alpha = th.tensor(self.alpha, device=q_matrix.device)
        return _pairwise_weights(alpha, self.n_critic_heads, self.n_actor_heads)


class DecayedConfidence(ConfidenceStrategy):
    """
    ``W[i, k] = d`` if ``i == k`` else ``(1 - d) / (K - 1)``, with ``d = max(1 / K, decay ** n_steps)``:
    from 1.0 down to 1/K, multiplied by ``decay`` at each environment step.

    :param decay: multiplicative decay per env-step, in (0, 1]
    """

    n_steps: th.Tensor

    def __init__(self, decay: float = 0.9995):
        super().__init__()
        self.decay = number(0.0, 1.0, True, False, "DecayedConfidence's decay per env step")("decay", decay)
        self.register_buffer("n_steps", th.zeros((), dtype=th.float64))

    @property
    def diagonal(self) -> float:
        """Current confidence ``d`` of a critic head in its own candidate."""
        return max(1.0 / max(self.n_critic_heads, 1), self.decay ** float(self.n_steps))

    def observe(self, step: ConfidenceStep) -> None:
        self.n_steps += len(step.rewards)

    def weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        return _pairwise_weights(th.tensor(self.diagonal, device=q_matrix.device), self.n_critic_heads, self.n_actor_heads)


class UCBConfidence(ConfidenceStrategy):
    """
    Optimistic selection (SUNRISE's UCB exploration, Lee et al., 2021): while exploring, each candidate is rated
    ``mean_i V[i, k] + ucb_lambda * std_i V[i, k]``, the mean of the critic heads' values plus a bonus for their
    disagreement; greedy actions (``predict(deterministic=True)``, evaluations) use the mean alone.

    As E-Critic weights: ``W[i, k] = 1 / Kc + ucb_lambda * (V[i, k] - mean_k) / (Kc * std_k)``, so that
    ``sum_i W[i, k] V[i, k] = mean_k + ucb_lambda * std_k`` (std over the critic heads, ddof 0).

    :param ucb_lambda: weight of the bonus, >= 0 (0: the mean of the heads)
    """

    def __init__(self, ucb_lambda: float = 1.0):
        super().__init__()
        self.ucb_lambda = number(0.0, math.inf, False, True, "UCBConfidence's weight of the bonus")("ucb_lambda", ucb_lambda)

    def weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        return th.full((1, self.n_critic_heads, self.n_actor_heads), 1.0 / self.n_critic_heads, device=q_matrix.device)

    def exploration_weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        mean = q_matrix.mean(dim=1, keepdim=True)  # (B, 1, Ka)
        std = q_matrix.std(dim=1, unbiased=False, keepdim=True)  # (B, 1, Ka)
        bonus = self.ucb_lambda * (q_matrix - mean) / (self.n_critic_heads * std.clamp(min=1e-8))
        return 1.0 / self.n_critic_heads + bonus  # (B, Kc, Ka)


class LCBConfidence(ConfidenceStrategy):
    """
    Pessimistic selection: each candidate is rated ``mean_i V[i, k] - kappa * std_i V[i, k]``, the mean of the critic
    heads' values less a multiple of their disagreement, whether exploring or acting greedily. The argmax over K
    candidates scored by K critics picks the candidate the critics overrate most (the E-action's own optimism, issue 19);
    a lower confidence bound counters it, as the minimum over critics does in TD3's target.

    As E-Critic weights: ``W[i, k] = 1 / Kc - kappa * (V[i, k] - mean_k) / (Kc * std_k)``, so that
    ``sum_i W[i, k] V[i, k] = mean_k - kappa * std_k`` (std over the critic heads, ddof 0).

    :param kappa: weight of the penalty, >= 0 (0: the mean of the heads)
    """

    def __init__(self, kappa: float = 1.0):
        super().__init__()
        self.kappa = number(0.0, math.inf, False, True, "LCBConfidence's weight of the penalty")("kappa", kappa)

    def weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        mean = q_matrix.mean(dim=1, keepdim=True)  # (B, 1, Ka)
        std = q_matrix.std(dim=1, unbiased=False, keepdim=True)  # (B, 1, Ka)
        penalty = self.kappa * (q_matrix - mean) / (self.n_critic_heads * std.clamp(min=1e-8))
        return 1.0 / self.n_critic_heads - penalty  # (B, Kc, Ka)


class ConfidenceNetwork(BaseModel):
    """
    The confidence module: shaped like a one-head actor (body [256], head [128]) with Kc sigmoid outputs
    clamped to [eps, 1].

    With ``share_features_extractor``, ``features_extractor`` is the actor's (the policy's
    ``share_features_extractor=True``): read without gradient, it is not the confidence network's to train
    (see :meth:`trained_parameters`).
    """

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        n_critic_heads: int,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module],
        normalize_images: bool = True,
        eps: float = 1e-3,
        share_features_extractor: bool = False,
    ):
        super().__init__(
            observation_space, action_space, features_extractor=features_extractor, normalize_images=normalize_images
        )
        self.net = mlp([features_dim, *net_arch], activation_fn)
        self.out = nn.Linear(net_arch[-1] if net_arch else features_dim, n_critic_heads)
        self.eps = eps
        self.share_features_extractor = share_features_extractor

    def trained_parameters(self) -> list[nn.Parameter]:
        """The parameters REINFORCE trains: all of them, less a features extractor shared with the actor."""
        if not self.share_features_extractor:
            return list(self.parameters())
        return [*self.net.parameters(), *self.out.parameters()]

    def forward(self, obs: PyTorchObs) -> th.Tensor:  # type: ignore[override]
        if self.share_features_extractor:
            with th.no_grad():
                features = self.extract_features(obs, self.features_extractor)  # type: ignore[arg-type]
        else:
            features = self.extract_features(obs, self.features_extractor)  # type: ignore[arg-type]
        return th.sigmoid(self.out(self.net(features))).clamp(self.eps, 1.0)  # (B, Kc)


TEMPERATURE_MODES = ("absolute", "relative")


class AdaptiveConfidence(ConfidenceStrategy):
    """
    Self-adaptive confidence (the paper's "SAC", eq. 8): ``W[i, k] = c_i(s)`` from a confidence network,
    trained by REINFORCE on the selections it made: the selection is read as the categorical policy
    ``pi_C(k | s) = softmax(v / temperature)[k]`` with ``v = sum_i c_i(s) V[i, k]`` (V detached) (or, with
    ``temperature_mode="relative"``, ``softmax((v - mean_k v) / (temperature * std_k v))``, which does not depend on
    the scale of the Q values), and
    ``log pi_C(k_t | s_t) * (r_t - b)`` is ascended, b a running mean of the reward (or 0 without baseline).

    :param lr: learning rate of the confidence network (Adam)
    :param temperature: softmax temperature of the selection policy, > 0
    :param temperature_mode: "absolute" (the temperature divides the E-Q values, whose scale is the reward's) or
        "relative" (it divides them in units of their spread across the candidates of the state)
    :param baseline: subtract a running-mean reward baseline (False: the paper's raw reward)
    :param baseline_rate: update rate of the running mean, in (0, 1]
    :param net_arch: hidden sizes of the confidence network (default [256, 128])
    :param eps: lower clamp of the confidence, in (0, 1)
    :param max_rollout: the most selections kept for the next update (the oldest are dropped when no training round
        comes to use them, e.g. ``gradient_steps=0``)
    """

    reward_baseline: th.Tensor
    baseline_pending: th.Tensor

    def __init__(
        self,
        lr: float = 1e-4,
        temperature: float = 1.0,
        baseline: bool = True,
        temperature_mode: str = "absolute",
        baseline_rate: float = 0.01,
        net_arch: list[int] | None = None,
        eps: float = 1e-3,
        max_rollout: int = 100_000,
    ):
        super().__init__()
        where = "AdaptiveConfidence's "
        self.lr = number(0.0, math.inf, True, True, where + "confidence network learning rate")("lr", lr)
        self.temperature = number(0.0, math.inf, True, True, where + "softmax temperature")("temperature", temperature)
        self.temperature_mode = choice(TEMPERATURE_MODES, where + "the temperature divides the E-Q values, or their spread")(
            "temperature_mode", temperature_mode
        )
        self.baseline = boolean(where + "running-mean reward baseline in REINFORCE")("baseline", baseline)
        self.baseline_rate = number(0.0, 1.0, True, False, where + "update rate of the baseline")(
            "baseline_rate", baseline_rate
        )
        self.eps = number(0.0, 1.0, True, True, where + "lower clamp of the confidence")("eps", eps)
        self.max_rollout = integer(1, where + "most selections kept between two updates")("max_rollout", max_rollout)
        self.net_arch = [256, 128] if net_arch is None else list(net_arch)
        self.register_buffer("reward_baseline", th.zeros(()))
        # 1.0 until the first update sets the baseline to its mean reward, then 0.0: a float (not a bool), as every
        # entry of the policy's state_dict, which SB3's tests and weight averaging treat as floats
        self.register_buffer("baseline_pending", th.ones(()))
        # The selections made since the last update, with their rewards: REINFORCE is on-policy
        self._rollout: list[ConfidenceStep] = []

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        # files saved before 0.2.0a0's issue 18 hold the bool "baseline_ready" instead of the float "baseline_pending"
        ready = state_dict.pop(prefix + "baseline_ready", None)
        if ready is not None and prefix + "baseline_pending" not in state_dict:
            state_dict[prefix + "baseline_pending"] = (~ready.bool()).float()
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def setup(self, policy: "SOUPPolicy") -> None:
        super().setup(policy)
        # its own features extractor, or the actor's when the policy shares it (share_features_extractor=True)
        shared = bool(getattr(policy, "share_features_extractor", False))
        extractor = policy.actor.features_extractor if shared else policy.make_features_extractor()
        assert extractor is not None
        self.network = ConfidenceNetwork(
            policy.observation_space,
            policy.action_space,
            self.n_critic_heads,
            self.net_arch,
            extractor,
            extractor.features_dim,
            policy.activation_fn,
            normalize_images=policy.normalize_images,
            eps=self.eps,
            share_features_extractor=shared,
        )
        # fused: one kernel for the step, where the default takes a dozen per parameter (0.1 ms against 0.5 on CPU)
        self.optimizer = th.optim.Adam(self.network.trained_parameters(), lr=self.lr, fused=True)

    def confidence(self, obs: PyTorchObs) -> th.Tensor:
        """Confidence vector ``c(s)`` of shape ``(B, Kc)`` in [eps, 1]."""
        return self.network(obs)

    def weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        return self.confidence(obs).unsqueeze(-1)  # (B, Kc, 1): the same c_i for every candidate

    def selection_logits(self, e_q: th.Tensor) -> th.Tensor:
        """
        :param e_q: ``(N, Ka)`` E-Q values of the candidates
        :return: ``(N, Ka)`` the logits of the selection policy ``pi_C``
        """
        if self.temperature_mode == "absolute":
            return e_q / self.temperature
        centered = e_q - e_q.mean(dim=1, keepdim=True)
        return centered / (self.temperature * e_q.std(dim=1, unbiased=False, keepdim=True).clamp(min=1e-6))

    def observe(self, step: ConfidenceStep) -> None:
        if step.q_matrix is None:
            return  # no selection: nothing to learn from
        self._rollout.append(step)
        if len(self._rollout) > self.max_rollout:  # no training round came to use them (e.g. gradient_steps=0)
            del self._rollout[0]

    def update(self) -> dict[str, float]:
        steps, self._rollout = self._rollout, []
        if self.n_actor_heads == 1 or not steps:
            return {}  # one candidate: the selection policy is constant, nothing to learn
        observations: PyTorchObs
        if isinstance(steps[0].observations, dict):
            observations = {key: th.cat([step.observations[key] for step in steps]) for key in steps[0].observations}  # type: ignore[index]
        else:
            observations = th.cat([step.observations for step in steps])  # type: ignore[misc]
        q_matrices = th.cat([step.q_matrix for step in steps])  # type: ignore[misc]  # (N, Kc, Ka)
        chosen = th.cat([step.chosen for step in steps])  # type: ignore[misc]  # (N,)
        return self._reinforce(observations, q_matrices, chosen, th.cat([step.rewards for step in steps]))

    def _reinforce(
        self, observations: PyTorchObs, q_matrices: th.Tensor, chosen: th.Tensor, rewards: th.Tensor
    ) -> dict[str, float]:
        """Eq. 8: one REINFORCE step on the selections ``chosen`` made from ``q_matrices``, and the ``rewards`` after them."""
        confidence = self.confidence(observations)  # (N, Kc)
        e_q = (confidence.unsqueeze(-1) * q_matrices).sum(dim=1)  # (N, Ka)
        logits = self.selection_logits(e_q)  # (N, Ka)
        log_prob = F.log_softmax(logits, dim=1)
        chosen_log_prob = log_prob.gather(1, chosen.long().unsqueeze(1)).squeeze(1)  # (N,)
        rewards = rewards.float()
        advantage = rewards - self.reward_baseline if self.baseline else rewards  # (N,)
        loss = -(chosen_log_prob * advantage).mean()
        with th.no_grad():  # how decided the selection policy is: near 1 saturated, near 1/Ka flat
            max_prob = log_prob.max(dim=1).values.exp().median()
            spread = logits.std(dim=1, unbiased=False).median()
        assert self.optimizer is not None, "setup() builds the optimizer"
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        if self.baseline:
            with th.no_grad():
                mean_reward = rewards.mean()
                if bool(self.baseline_pending > 0.5):
                    self.reward_baseline.copy_(mean_reward)
                    self.baseline_pending.fill_(0.0)
                else:
                    self.reward_baseline.lerp_(mean_reward, self.baseline_rate)
        return {
            "confidence_loss": loss.item(),
            "confidence_baseline": float(self.reward_baseline),
            "selection_max_prob": float(max_prob),
            "selection_logit_spread": float(spread),
        }


def check_update_logs(strategy: ConfidenceStrategy, logs: Any) -> dict[str, float]:
    """
    :param strategy: the strategy whose :meth:`ConfidenceStrategy.update` returned ``logs``
    :param logs: what it returned
    :return: ``logs``, once checked to be a dict of names to numbers
    """
    if not isinstance(logs, dict) or not all(isinstance(key, str) for key in logs):
        raise ValueError(
            f"{type(strategy).__name__}.update must return a dict of values to log (name -> float; {{}} for none), "
            f"got {logs!r} ({type(logs).__name__})"
        )
    return logs


STRATEGIES: dict[str, type[ConfidenceStrategy]] = {
    "none": NoConfidence,
    "fixed": FixedConfidence,
    "decayed": DecayedConfidence,
    "adaptive": AdaptiveConfidence,
    "ucb": UCBConfidence,
    "lcb": LCBConfidence,
}
"""The strategies SOUP's ``confidence`` names; ``confidence_kwargs`` are the named class's own arguments."""
CONFIDENCE_STRATEGIES = tuple(STRATEGIES)


def _strategy_arguments(strategy_class: type[ConfidenceStrategy]) -> list[str]:
    """The keyword arguments a strategy class takes (those of its ``__init__``)."""
    keywords = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    parameters = inspect.signature(strategy_class.__init__).parameters.items()
    return sorted(name for name, parameter in parameters if name != "self" and parameter.kind in keywords)


def check_confidence(confidence: Any, name: str = "confidence") -> "str | ConfidenceStrategy":
    """
    :param confidence: a strategy's name (any case) or a :class:`ConfidenceStrategy` instance
    :param name: the argument's name, for the message
    :return: the name in lower case, or the instance
    """
    accepted = f"one of {CONFIDENCE_STRATEGIES} or an instance of a sb3_soup.ConfidenceStrategy subclass"
    if isinstance(confidence, str):
        if confidence.lower() not in STRATEGIES:
            raise ValueError(f"{name} must be {accepted}, {given(confidence)}")
        return confidence.lower()
    if not isinstance(confidence, ConfidenceStrategy):
        hint = (
            " (it has a weights method: subclass sb3_soup.ConfidenceStrategy, an nn.Module, so that its state is saved)"
            if callable(getattr(confidence, "weights", None))
            else ""
        )
        raise ValueError(f"{name} must be {accepted} implementing weights(obs, q_matrix) -> W, {given(confidence)}{hint}")
    if "_parameters" not in vars(confidence):
        raise ValueError(
            f"{name}: {type(confidence).__name__}.__init__ must call super().__init__() "
            "(a ConfidenceStrategy is an nn.Module, whose state is saved with the policy)"
        )
    return confidence


def make_confidence(
    confidence: "str | ConfidenceStrategy", confidence_kwargs: dict[str, Any] | None = None
) -> ConfidenceStrategy:
    """
    Build a strategy from its name and its own keyword arguments (the class's defaults for the others), or check a
    user's strategy object.

    :param confidence: "none", "fixed", "decayed", "adaptive", "ucb", "lcb" (see :data:`STRATEGIES`), or a
        :class:`ConfidenceStrategy` instance
    :param confidence_kwargs: the named strategy's arguments, e.g. ``dict(alpha=0.7)`` for "fixed" (None: its defaults);
        none with an instance, which has its own
    :return: the strategy
    """
    confidence = check_confidence(confidence)
    if confidence_kwargs is not None and not isinstance(confidence_kwargs, dict):
        raise ValueError(f"confidence_kwargs must be None or a dict of the strategy's arguments, {given(confidence_kwargs)}")
    if isinstance(confidence, ConfidenceStrategy):
        if confidence_kwargs:
            raise ValueError(
                f"confidence_kwargs {sorted(confidence_kwargs)} cannot be given with a strategy instance "
                f"({type(confidence).__name__}): set them when creating it"
            )
        return confidence
    strategy_class = STRATEGIES[confidence]
    accepted = _strategy_arguments(strategy_class)
    unknown = sorted(set(confidence_kwargs or {}) - set(accepted))
    if unknown:
        raise ValueError(
            f"confidence_kwargs has unknown keys {unknown} for confidence={confidence!r}: {strategy_class.__name__} "
            f"accepts {accepted}"
        )
    return strategy_class(**(confidence_kwargs or {}))
