"""
Confidence strategies (Section 5.2 of the paper): the weight matrix ``W`` of the E-Critic layer.

The E-Q value of candidate k is ``v[k] = sum_i W[i, k] * V[i, k]`` where ``V[i, k] = Q_i(s, a^k)``
(critic head i scores candidate k). A strategy is an ``nn.Module`` so that its parameters and state
(a decay counter, a reward baseline) are saved, loaded and moved to the device with the policy.

Write your own by subclassing :class:`ConfidenceStrategy` and implementing :meth:`ConfidenceStrategy.weights`.
"""

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
from sb3_soup.validation import check_bool, check_float

if TYPE_CHECKING:
    from sb3_soup.policies import SOUPPolicy

CONFIDENCE_STRATEGIES = ("none", "fixed", "decayed", "adaptive", "ucb")


class ConfidenceRollout(NamedTuple):
    """The selections made while acting since the last update (all envs), for on-policy strategies."""

    observations: PyTorchObs  # (N, *obs_shape) or a dict of them
    q_matrices: th.Tensor  # (N, Kc, Ka), detached
    chosen: th.Tensor  # (N,) index of the executed candidate
    rewards: th.Tensor  # (N,) reward that followed


class ConfidenceStrategy(nn.Module, ABC):
    """
    Interface of a confidence strategy.

    - :meth:`weights` gives ``W`` (shape ``(B, Kc, Ka)``, or broadcastable to it) for a batch of observations;
    - :meth:`exploration_weights` gives the ``W`` used while exploring (``learn``, ``predict(deterministic=False)``),
      by default the same;
    - :meth:`on_step` is called once per vectorised environment step during ``learn``;
    - :meth:`update` is called after each training round with the selections made since the previous one
      when :attr:`needs_rollout` is True, and returns values to log;
    - anything to save goes in parameters/buffers (saved with the policy) or :attr:`optimizer` (saved with the model).
    """

    needs_rollout: bool = False
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

    def on_step(self, n_env_steps: int) -> None:
        """Called after each vectorised environment step during ``learn`` with the number of env-steps taken."""

    def update(self, rollout: ConfidenceRollout) -> dict[str, float]:
        """Learn from the selections made since the last update; return values to log (``train/<key>``)."""
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


class _PairedStrategy(ConfidenceStrategy):
    """Strategies that weight critic head i on its own candidate i: need as many critic as actor heads (or one)."""

    def setup(self, policy: "SOUPPolicy") -> None:
        super().setup(policy)
        n_critic, n_actor = self.n_critic_heads, self.n_actor_heads
        if n_critic != n_actor and n_critic > 1 and n_actor > 1:
            raise ValueError(
                f"confidence={self.name!r} pairs critic head i with candidate i: it needs n_critic_heads == n_actor_heads "
                f"(or one of them 1), got n_critic_heads={n_critic}, n_actor_heads={n_actor}; use 'none' or 'adaptive'"
            )

    name = "paired"


class FixedConfidence(_PairedStrategy):
    """
    ``W[i, k] = alpha`` if ``i == k`` else ``(1 - alpha) / (K - 1)``.

    :param alpha: confidence of a critic head in its own actor head's candidate, in (0, 1)
    """

    name = "fixed"

    def __init__(self, alpha: float = 0.5):
        super().__init__()
        self.alpha = check_float("alpha", alpha, 0.0, 1.0, True, True, "fixed confidence of a head in its own candidate")

    def weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        alpha = th.tensor(self.alpha, device=q_matrix.device)
        return _pairwise_weights(alpha, self.n_critic_heads, self.n_actor_heads)


class DecayedConfidence(_PairedStrategy):
    """
    ``W[i, k] = d`` if ``i == k`` else ``(1 - d) / (K - 1)``, with ``d = max(1 / K, decay ** n_steps)``:
    from 1.0 down to 1/K, multiplied by ``decay`` at each environment step.

    :param decay: multiplicative decay per env-step, in (0, 1]
    """

    name = "decayed"
    n_steps: th.Tensor

    def __init__(self, decay: float = 0.9995):
        super().__init__()
        self.decay = check_float("decay", decay, 0.0, 1.0, True, False, "per-step decay of the decayed confidence")
        self.register_buffer("n_steps", th.zeros((), dtype=th.float64))

    @property
    def diagonal(self) -> float:
        """Current confidence ``d`` of a critic head in its own candidate."""
        return max(1.0 / max(self.n_critic_heads, 1), self.decay ** float(self.n_steps))

    def on_step(self, n_env_steps: int) -> None:
        self.n_steps += n_env_steps

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

    name = "ucb"

    def __init__(self, ucb_lambda: float = 1.0):
        super().__init__()
        self.ucb_lambda = check_float("ucb_lambda", ucb_lambda, 0.0, math.inf, False, True, "weight of the UCB bonus")

    def weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        return th.full((1, self.n_critic_heads, self.n_actor_heads), 1.0 / self.n_critic_heads, device=q_matrix.device)

    def exploration_weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        mean = q_matrix.mean(dim=1, keepdim=True)  # (B, 1, Ka)
        std = q_matrix.std(dim=1, unbiased=False, keepdim=True)  # (B, 1, Ka)
        bonus = self.ucb_lambda * (q_matrix - mean) / (self.n_critic_heads * std.clamp(min=1e-8))
        return 1.0 / self.n_critic_heads + bonus  # (B, Kc, Ka)


class ConfidenceNetwork(BaseModel):
    """
    The confidence module: shaped like a one-head actor (body [256], head [128]) with Kc sigmoid outputs
    clamped to [eps, 1].
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
    ):
        super().__init__(
            observation_space, action_space, features_extractor=features_extractor, normalize_images=normalize_images
        )
        self.net = mlp([features_dim, *net_arch], activation_fn)
        self.out = nn.Linear(net_arch[-1] if net_arch else features_dim, n_critic_heads)
        self.eps = eps

    def forward(self, obs: PyTorchObs) -> th.Tensor:  # type: ignore[override]
        features = self.extract_features(obs, self.features_extractor)  # type: ignore[arg-type]
        return th.sigmoid(self.out(self.net(features))).clamp(self.eps, 1.0)  # (B, Kc)


class AdaptiveConfidence(ConfidenceStrategy):
    """
    Self-adaptive confidence (the paper's "SAC", eq. 8): ``W[i, k] = c_i(s)`` from a confidence network,
    trained by REINFORCE on the selections it made: the selection is read as the categorical policy
    ``pi_C(k | s) = softmax(v / temperature)[k]`` with ``v = sum_i c_i(s) V[i, k]`` (V detached), and
    ``log pi_C(k_t | s_t) * (r_t - b)`` is ascended, b a running mean of the reward (or 0 without baseline).

    :param lr: learning rate of the confidence network (Adam)
    :param temperature: softmax temperature of the selection policy, > 0
    :param baseline: subtract a running-mean reward baseline (False: the paper's raw reward)
    :param baseline_rate: update rate of the running mean, in (0, 1]
    :param net_arch: hidden sizes of the confidence network (default [256, 128])
    :param eps: lower clamp of the confidence, in (0, 1)
    """

    needs_rollout = True
    reward_baseline: th.Tensor
    baseline_ready: th.Tensor

    def __init__(
        self,
        lr: float = 1e-4,
        temperature: float = 1.0,
        baseline: bool = True,
        baseline_rate: float = 0.01,
        net_arch: list[int] | None = None,
        eps: float = 1e-3,
    ):
        super().__init__()
        self.lr = check_float("confidence_lr", lr, 0.0, math.inf, True, True, "confidence network learning rate")
        self.temperature = check_float(
            "temperature", temperature, 0.0, math.inf, True, True, "softmax temperature of the selection"
        )
        self.baseline = check_bool("confidence_baseline", baseline, "running-mean reward baseline in REINFORCE")
        self.baseline_rate = check_float("baseline_rate", baseline_rate, 0.0, 1.0, True, False, "update rate of the baseline")
        self.eps = check_float("eps", eps, 0.0, 1.0, True, True, "lower clamp of the confidence")
        self.net_arch = [256, 128] if net_arch is None else list(net_arch)
        self.register_buffer("reward_baseline", th.zeros(()))
        self.register_buffer("baseline_ready", th.zeros((), dtype=th.bool))

    def setup(self, policy: "SOUPPolicy") -> None:
        super().setup(policy)
        extractor = policy.make_features_extractor()
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
        )
        self.optimizer = th.optim.Adam(self.network.parameters(), lr=self.lr)

    def confidence(self, obs: PyTorchObs) -> th.Tensor:
        """Confidence vector ``c(s)`` of shape ``(B, Kc)`` in [eps, 1]."""
        return self.network(obs)

    def weights(self, obs: PyTorchObs, q_matrix: th.Tensor) -> th.Tensor:
        return self.confidence(obs).unsqueeze(-1)  # (B, Kc, 1): the same c_i for every candidate

    def update(self, rollout: ConfidenceRollout) -> dict[str, float]:
        if self.n_actor_heads == 1:
            return {}  # one candidate: the selection policy is constant, nothing to learn
        confidence = self.confidence(rollout.observations)  # (N, Kc)
        e_q = (confidence.unsqueeze(-1) * rollout.q_matrices).sum(dim=1)  # (N, Ka)
        log_prob = F.log_softmax(e_q / self.temperature, dim=1)  # (N, Ka)
        chosen_log_prob = log_prob.gather(1, rollout.chosen.long().unsqueeze(1)).squeeze(1)  # (N,)
        rewards = rollout.rewards.float()
        advantage = rewards - self.reward_baseline if self.baseline else rewards  # (N,)
        loss = -(chosen_log_prob * advantage).mean()
        with th.no_grad():  # how decided the selection policy is: near 1 saturated, near 1/Ka flat
            max_prob = log_prob.max(dim=1).values.exp().median()
            spread = (e_q / self.temperature).std(dim=1, unbiased=False).median()
        assert self.optimizer is not None, "setup() builds the optimizer"
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        if self.baseline:
            with th.no_grad():
                mean_reward = rewards.mean()
                if bool(self.baseline_ready):
                    self.reward_baseline.lerp_(mean_reward, self.baseline_rate)
                else:
                    self.reward_baseline.copy_(mean_reward)
                    self.baseline_ready.fill_(True)
        return {
            "confidence_loss": loss.item(),
            "confidence_baseline": float(self.reward_baseline),
            "selection_max_prob": float(max_prob),
            "selection_logit_spread": float(spread),
        }


def check_strategy(confidence: Any) -> None:
    """
    Refuse, with a message saying what is expected, anything that is neither a strategy name nor a usable
    :class:`ConfidenceStrategy` instance.

    :param confidence: "none", "fixed", "decayed", "adaptive" (any case), or a :class:`ConfidenceStrategy` instance
    """
    accepted = f"one of {CONFIDENCE_STRATEGIES} or an instance of a sb3_soup.ConfidenceStrategy subclass"
    if isinstance(confidence, str):
        if confidence.lower() not in CONFIDENCE_STRATEGIES:
            raise ValueError(f"confidence must be {accepted}, got {confidence!r}")
        return
    if not isinstance(confidence, ConfidenceStrategy):
        hint = (
            " (it has a weights method: subclass sb3_soup.ConfidenceStrategy, an nn.Module, so that its state is saved)"
            if callable(getattr(confidence, "weights", None))
            else ""
        )
        raise ValueError(
            f"confidence must be {accepted} implementing weights(obs, q_matrix) -> W, "
            f"got {confidence!r} of type {type(confidence).__name__}{hint}"
        )
    if "_parameters" not in vars(confidence):
        raise ValueError(
            f"confidence: {type(confidence).__name__}.__init__ must call super().__init__() "
            "(a ConfidenceStrategy is an nn.Module, whose state is saved with the policy)"
        )


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


def make_confidence(confidence: "str | ConfidenceStrategy", **kwargs: Any) -> ConfidenceStrategy:
    """
    Build a strategy from its name (keyword arguments are passed to it; unused ones are ignored) or check a
    user's strategy object.

    :param confidence: "none", "fixed", "decayed", "adaptive", or a :class:`ConfidenceStrategy` instance
    """
    check_strategy(confidence)
    if isinstance(confidence, ConfidenceStrategy):
        return confidence
    name = confidence.lower()
    if name == "none":
        return NoConfidence()
    if name == "fixed":
        return FixedConfidence(alpha=kwargs.get("alpha", 0.5))
    if name == "decayed":
        return DecayedConfidence(decay=kwargs.get("decay", 0.9995))
    if name == "ucb":
        return UCBConfidence(ucb_lambda=kwargs.get("ucb_lambda", 1.0))
    return AdaptiveConfidence(
        lr=kwargs.get("lr", 1e-4), temperature=kwargs.get("temperature", 1.0), baseline=kwargs.get("baseline", True)
    )
