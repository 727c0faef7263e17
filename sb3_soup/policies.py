"""SOUP policy: bootstrapped actor and critic, their targets, the confidence strategy, and the ensemble selection."""

import inspect
import warnings
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, FlattenExtractor, NatureCNN
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_soup.confidence import ConfidenceStrategy, check_confidence, make_confidence
from sb3_soup.networks import EnsembleActor, EnsembleCritic, HeadIndex
from sb3_soup.optim import EnsembleAdam, ensemble_param_groups
from sb3_soup.validation import boolean, check_head_counts, integer, outside_stacklevel

# The paper's sizes (Section 5): actor (256, **128**), critic (256, 256, **128**), bold = head layer.
DEFAULT_NET_ARCH: dict[str, list[int]] = dict(pi_body=[256], pi_head=[128], qf_body=[256, 256], qf_head=[128])
# The critic body layer the action joins: 1, the second (the paper's DDPG critic), 0, the input (SB3's critic)
DEFAULT_ACTION_LAYER = 1
SOUP_NET_ARCH_KEYS = (*DEFAULT_NET_ARCH, "qf_action_layer")
NetArch = list[int] | dict[str, Any]
# The policy's arguments that SOUP sets from its own (head counts, confidence strategy), besides policy_kwargs
SET_BY_SOUP = ("n_actor_heads", "n_critic_heads", "confidence", "confidence_kwargs")


class ObservationSpaceError(ValueError, AssertionError):
    """
    The policy does not fit the observation space (``CnnPolicy``/``NatureCNN`` on observations that are not images,
    ``MultiInputPolicy`` on observations that are not a Dict). A ``ValueError`` (SOUP's rule for bad input) and an
    ``AssertionError``, what SB3's TD3 and DDPG raise there (``NatureCNN``'s assertion), so that code written for them,
    ``pytest.raises(AssertionError)`` in SB3's tests included, catches it.
    """


def _layer_sizes(name: str, sizes: Any, example: list[int]) -> list[int]:
    valid = isinstance(sizes, (list, tuple)) and all(
        isinstance(size, (int, np.integer)) and not isinstance(size, (bool, np.bool_)) and size > 0 for size in sizes
    )
    if not valid:
        raise ValueError(f"{name} must be a list of positive ints (layer sizes), e.g. {example}; got {sizes!r}")
    return [int(size) for size in sizes]


def _split_hidden_layers(sizes: list[int]) -> tuple[list[int], list[int]]:
    """SB3's hidden layers as SOUP's (shared body, per-head layers): every layer but the last, and the last."""
    return sizes[:-1], sizes[-1:]


def parse_net_arch(net_arch: NetArch | None, default_action_layer: int | None = None) -> dict[str, Any]:
    """
    ``net_arch`` in SOUP's form: the shared bodies and the K heads of actor and critic, and where the action joins the
    critic. Three forms are accepted:

    - SOUP's: ``dict(pi_body=[256], pi_head=[128], qf_body=[256, 256], qf_head=[128], qf_action_layer=1)`` (the
      paper's sizes, the default; missing keys take the default; ``qf_action_layer``: 1, the action joins the critic at
      its second body layer, as in the paper's DDPG; 0, at its input, as in SB3);
    - SB3's list, ``[400, 300]``: the hidden layers of the actor and of the critic (as TD3's and DDPG's);
    - SB3's ``dict(pi=[400, 300], qf=[400, 300])``: the actor's and the critic's hidden layers.

    SB3's forms map onto SOUP's by one rule: every hidden layer but the last is the shared body, the last is each
    head's own hidden layer (``[400, 300]``: body [400], heads [300] -> output; ``[64]``: no body, heads [64];
    ``[]``: linear heads), and the critic takes the action with the observation's features at its input, as SB3's
    ``ContinuousCritic``. With one head, the networks are SB3's.

    :param net_arch: one of the forms above, or None (the default)
    :param default_action_layer: ``qf_action_layer`` where SOUP's form leaves it out (``None``:
        :data:`DEFAULT_ACTION_LAYER`), e.g. the default of an earlier version, to read what one of its runs built
    :return: SOUP's form, every key set
    """
    if net_arch is None:
        net_arch = {}
    if isinstance(net_arch, (list, tuple)):
        body, head = _split_hidden_layers(_layer_sizes("net_arch", net_arch, [400, 300]))
        return dict(pi_body=body, pi_head=head, qf_body=list(body), qf_head=list(head), qf_action_layer=0)
    if not isinstance(net_arch, dict):
        raise ValueError(
            "net_arch must be a list of layer sizes (SB3's form, e.g. [400, 300]), a dict(pi=[...], qf=[...]) (SB3's), "
            f"or a dict with keys {list(SOUP_NET_ARCH_KEYS)} (SOUP's bodies and heads, e.g. {DEFAULT_NET_ARCH}); "
            f"got {net_arch!r}"
        )
    sb3_keys = {"pi", "qf"}
    if set(net_arch) & sb3_keys:
        if set(net_arch) != sb3_keys:
            raise ValueError(
                f"net_arch in SB3's dict form needs the keys ['pi', 'qf'] and no other (SOUP's form takes "
                f"{list(SOUP_NET_ARCH_KEYS)}), got keys {sorted(net_arch)}"
            )
        pi_body, pi_head = _split_hidden_layers(_layer_sizes("net_arch['pi']", net_arch["pi"], [400, 300]))
        qf_body, qf_head = _split_hidden_layers(_layer_sizes("net_arch['qf']", net_arch["qf"], [400, 300]))
        return dict(pi_body=pi_body, pi_head=pi_head, qf_body=qf_body, qf_head=qf_head, qf_action_layer=0)
    unknown = set(net_arch) - set(SOUP_NET_ARCH_KEYS)
    if unknown:
        raise ValueError(
            f"net_arch has unknown keys {sorted(unknown)}; accepted keys: {list(SOUP_NET_ARCH_KEYS)} (SOUP's form), or "
            "['pi', 'qf'] (SB3's dict form), or a list of layer sizes (SB3's)"
        )
    arch: dict[str, Any] = {}
    for key, default in DEFAULT_NET_ARCH.items():
        arch[key] = _layer_sizes(f"net_arch[{key!r}]", net_arch.get(key, default), default)
    default_layer = DEFAULT_ACTION_LAYER if default_action_layer is None else default_action_layer
    action_layer = net_arch.get("qf_action_layer", default_layer)
    is_int = isinstance(action_layer, (int, np.integer)) and not isinstance(action_layer, (bool, np.bool_))
    if not is_int or action_layer not in (0, 1):
        raise ValueError(
            "net_arch['qf_action_layer'] must be 0 (the action joins the critic at its input, as in SB3) or 1 (at its "
            f"second body layer, the paper's DDPG critic), got {action_layer!r}"
        )
    if action_layer == 1 and len(arch["qf_body"]) < 2:
        raise ValueError(
            f"net_arch['qf_body'] needs at least 2 layers (the action joins at the second), got {arch['qf_body']}; "
            "with net_arch['qf_action_layer']=0 the action joins at the input (SB3's critic) and any body goes"
        )
    arch["qf_action_layer"] = int(action_layer)
    return arch


def check_weights(strategy: ConfidenceStrategy, weights: Any, q_matrix: th.Tensor) -> None:
    """
    Refuse what a confidence strategy's ``weights`` returned when it is not a tensor broadcastable to ``V``
    (a few attribute reads: no device synchronisation).

    :param strategy: the strategy
    :param weights: what its ``weights(obs, q_matrix)`` returned
    :param q_matrix: ``V`` of shape ``(B, Kc, Ka)``
    """
    if not isinstance(weights, th.Tensor):
        raise ValueError(
            f"{type(strategy).__name__}.weights must return a torch.Tensor broadcastable to (B, Kc, Ka) = "
            f"{tuple(q_matrix.shape)}, got {type(weights).__name__}"
        )
    try:
        broadcastable = th.broadcast_shapes(weights.shape, q_matrix.shape) == q_matrix.shape
    except RuntimeError:
        broadcastable = False
    if not broadcastable:
        raise ValueError(
            f"{type(strategy).__name__}.weights returned shape {tuple(weights.shape)}, "
            f"expected one broadcastable to (B, Kc, Ka) = {tuple(q_matrix.shape)}"
        )


def e_critic(q_matrix: th.Tensor, weights: th.Tensor) -> th.Tensor:
    """
    E-Critic layer (eq. 7): E-Q value of each candidate, ``v[k] = sum_i W[i, k] * V[i, k]``.

    :param q_matrix: ``V`` of shape ``(B, Kc, Ka)``
    :param weights: ``W``, broadcastable to ``V``
    :return: ``v`` of shape ``(B, Ka)``
    """
    return (weights * q_matrix).sum(dim=1)


def e_actor(candidates: th.Tensor, e_q: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """
    E-Actor layer (eq. 7): the candidate with the highest E-Q value.

    :param candidates: ``(Ka, B, A)``
    :param e_q: ``(B, Ka)``
    :return: the E-actions ``(B, A)`` and the chosen candidate indices ``(B,)``
    """
    chosen = e_q.argmax(dim=1)  # (B,)
    return candidates[chosen, th.arange(candidates.shape[1], device=candidates.device)], chosen


def check_n_critics(n_critics: Any, n_critic_heads: int) -> None:
    """
    SB3's ``n_critics`` (TD3Policy, SACPolicy) in SOUP: each critic head is one critic, as ``n_critics=1`` makes in SB3,
    and the number of critics is ``n_critic_heads``. 1 is accepted silently; more are ignored with a warning.

    :param n_critics: what the user passed in ``policy_kwargs``
    :param n_critic_heads: the policy's critic heads
    """
    n_critics = integer(1, "SB3's number of critics; SOUP's critics are its n_critic_heads")("n_critics", n_critics)
    if n_critics > 1:
        warnings.warn(
            f"policy_kwargs n_critics={n_critics} is ignored: SOUP's critics are its {n_critic_heads} critic heads "
            "(n_critic_heads, each one critic as SB3's n_critics=1 builds); TD3's clipped double Q is SOUP's "
            "default target_q='min_pair' (the smaller of a head's target and another head's)",
            UserWarning,
            stacklevel=outside_stacklevel(),
        )


def check_policy(
    policy_class: Any, policy_kwargs: dict[str, Any], observation_space: spaces.Space, aliases: list[str]
) -> None:
    """
    What SB3's checks let through but SOUP refuses: a policy that is not a :class:`SOUPPolicy`, unknown
    ``policy_kwargs``, ``MultiInputPolicy`` on non-Dict observations, ``CnnPolicy`` on observations that are not images;
    and a warning when image pixels go into an MLP.

    :param policy_class: the policy class
    :param policy_kwargs: its keyword arguments (SOUP's own included)
    :param observation_space: the env's observation space
    :param aliases: the policy names SOUP accepts
    """
    if not (isinstance(policy_class, type) and issubclass(policy_class, SOUPPolicy)):
        raise ValueError(f"policy must be one of {aliases} or a sb3_soup.SOUPPolicy subclass, got {policy_class!r}")
    accepted = inspect.signature(policy_class.__init__).parameters
    if not any(parameter.kind == inspect.Parameter.VAR_KEYWORD for parameter in accepted.values()):
        names = sorted(set(accepted) - {"self", "observation_space", "action_space", "lr_schedule"} - set(SET_BY_SOUP))
        unknown = sorted(set(policy_kwargs) - set(names) - set(SET_BY_SOUP))
        if unknown:
            raise ValueError(f"policy_kwargs has unknown keys {unknown}; {policy_class.__name__} accepts {names}")
    if issubclass(policy_class, MultiInputPolicy) and not isinstance(observation_space, spaces.Dict):
        raise ObservationSpaceError(
            f"policy must be 'MlpPolicy' for {observation_space} observations ('MultiInputPolicy' is for Dict)"
        )
    # the extractor asked for, or the policy's default (FlattenExtractor for MlpPolicy, NatureCNN for CnnPolicy)
    extractor = policy_kwargs.get("features_extractor_class") or policy_class.default_features_extractor_class
    normalized_image = (policy_kwargs.get("features_extractor_kwargs") or {}).get("normalized_image", False)
    if not policy_kwargs.get("normalize_images", True) and isinstance(extractor, type):
        # as SB3's BasePolicy: with normalize_images=False, NatureCNN and CombinedExtractor take float images as they are
        normalized_image = normalized_image or issubclass(extractor, (NatureCNN, CombinedExtractor))
    if extractor is NatureCNN and not is_image_space(
        observation_space, check_channels=False, normalized_image=normalized_image
    ):
        if "features_extractor_class" in policy_kwargs:
            parameter = "policy_kwargs['features_extractor_class']=NatureCNN"
        else:
            parameter = "policy='CnnPolicy'" if issubclass(policy_class, CnnPolicy) else f"policy={policy_class.__name__}"
        raise ObservationSpaceError(
            f"{parameter}: NatureCNN (CnnPolicy's features extractor) takes image observations: a Box of shape "
            "(C, H, W) or (H, W, C), uint8 in [0, 255] (or float, already normalised, with "
            f"policy_kwargs=dict(normalize_images=False)), got {observation_space}; use policy='MlpPolicy' (or "
            "'MultiInputPolicy' for Dict observations, whose image keys get a NatureCNN)"
        )
    if is_image_space(observation_space, check_channels=False) and extractor is FlattenExtractor:
        warnings.warn(
            f"the observations are images {observation_space.shape}: MlpPolicy flattens their pixels (scaled to "
            "[0, 1]) into the MLP, as SB3's DDPG does. For a CNN (NatureCNN) use policy='CnnPolicy'",
            UserWarning,
            stacklevel=outside_stacklevel(),
        )


class TrainedHeads(NamedTuple):
    """The heads of one network (actor or critic) that serve a list of head pairs being trained."""

    per_pair: list[int]  # (H,) the head serving each pair
    # what the network's forward takes: an int for one pair (outputs (B, ...), which broadcast as (1, B, ...)), None for
    # all its heads in order or its only head, else the tensor of per_pair
    head_arg: HeadIndex
    rows: int | th.Tensor | None  # the heads trained, for EnsembleAdam and soft_update: one, a (K,) bool mask, None: all


class Selection(NamedTuple):
    """What the ensemble decided for a batch of observations."""

    actions: th.Tensor  # (B, A) E-actions in [-1, 1]
    chosen: th.Tensor  # (B,) index of the chosen candidate
    q_matrix: th.Tensor | None  # (B, Kc, Ka), None when there is one actor and one critic head
    weights: th.Tensor | None  # W broadcastable to (B, Kc, Ka)
    candidates: th.Tensor | None = None  # (Ka, B, A) every actor head's action in [-1, 1]


class EnsembleView(NamedTuple):
    """
    The ensemble's view of a batch of observations (:meth:`SOUPPolicy.ensemble_view`), as NumPy arrays, batch first.
    Actions are in the environment's bounds, as ``predict`` returns them. For an unbatched observation (as
    ``predict`` takes it) the leading ``B`` is dropped from every field.
    """

    actions: np.ndarray  # (B, A) the E-action executed: predict(obs, deterministic=True)'s action
    candidates: np.ndarray  # (B, Ka, A) the action of every actor head
    q_matrix: np.ndarray  # (B, Kc, Ka) V[b, i, k] = Q_i(s_b, a_b^k): every critic head's value of every candidate
    weights: np.ndarray  # (B, Kc, Ka) the confidence weights W of the E-Critic layer (eq. 7)
    e_q: np.ndarray  # (B, Ka) E-Q value of each candidate, v[k] = sum_i W[i, k] V[i, k]
    chosen: np.ndarray  # (B,) the actor head whose candidate is executed (argmax of e_q)
    q_mean: np.ndarray  # (B,) mean over the critic heads of the chosen candidate's Q value
    q_spread: np.ndarray  # (B,) their std (ddof 1, as the rollout/q_spread log; 0 with one critic head)


class SOUPPolicy(BasePolicy):
    """
    Policy class (actor, critic and their targets, confidence strategy) for SOUP.
    ``_predict`` performs the E-Critic/E-Actor selection, so ``predict``, ``evaluate_policy`` and
    ``EvalCallback`` act with the whole ensemble.

    :param observation_space: Observation space
    :param action_space: Action space (Box)
    :param lr_schedule: Learning rate schedule (could be constant)
    :param net_arch: body and head sizes: SOUP's ``dict(pi_body=[256], pi_head=[128], qf_body=[256, 256],
        qf_head=[128])`` (the paper's, default; missing keys take the default), or SB3's forms, a list of hidden layers
        (``[400, 300]``) or ``dict(pi=[...], qf=[...])``, whose last hidden layer is each head's and the others the shared
        body (see :func:`parse_net_arch`)
    :param activation_fn: Activation function (LeakyReLU, as in the paper)
    :param n_actor_heads: number of actor heads
    :param n_critic_heads: number of critic heads
    :param confidence: confidence strategy: "none", "fixed", "decayed", "adaptive", "ucb", "lcb" or a ConfidenceStrategy
        instance
    :param confidence_kwargs: keyword arguments of the named strategy's class (e.g. ``dict(alpha=0.7)`` for "fixed", see
        :data:`sb3_soup.confidence.STRATEGIES`); None with an instance
    :param features_extractor_class: Features extractor to use (None: the policy class's
        ``default_features_extractor_class``: ``FlattenExtractor``, ``NatureCNN`` for CnnPolicy, ``CombinedExtractor``
        for MultiInputPolicy)
    :param features_extractor_kwargs: Keyword arguments to pass to the features extractor.
    :param normalize_images: Whether to normalize images or not, dividing by 255.0 (True by default)
    :param optimizer_class: The optimizer to use (``EnsembleAdam`` keeps per-head state, so training one head
        leaves the others untouched)
    :param optimizer_kwargs: Additional keyword arguments, excluding the learning rate, to pass to the optimizer
        (``EnsembleAdam`` takes ``torch.optim.Adam``'s)
    :param share_features_extractor: one features extractor for the actor, the critic and the adaptive confidence
        network, as SB3's ``share_features_extractor``: the actor's loss trains it (the critic and the confidence
        network read its features without gradient) and the actor's soft update moves its target. False (the default,
        as SB3's TD3): each network has its own, trained by its own loss
    :param n_critics: SB3's number of critic networks (TD3Policy's argument): SOUP's critics are its ``n_critic_heads``,
        each head one critic as SB3's ``n_critics=1`` builds; 1 is accepted, more warn and are ignored (TD3's clipped
        double Q across the heads: SOUP's ``target_q="min_pair"``, the default)
    :param layer_norm: a LayerNorm after each linear layer of the critic's shared body, before its activation (SBX's
        name; unlike SBX's, the heads' hidden layers have none); False (the default): none
    """

    actor: EnsembleActor
    actor_target: EnsembleActor
    critic: EnsembleCritic
    critic_target: EnsembleCritic
    confidence: ConfidenceStrategy
    default_features_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        net_arch: NetArch | None = None,
        activation_fn: type[nn.Module] = nn.LeakyReLU,
        n_actor_heads: int = 5,
        n_critic_heads: int = 5,
        confidence: "str | ConfidenceStrategy" = "adaptive",
        confidence_kwargs: dict[str, Any] | None = None,
        features_extractor_class: type[BaseFeaturesExtractor] | None = None,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = EnsembleAdam,
        optimizer_kwargs: dict[str, Any] | None = None,
        share_features_extractor: bool = False,
        n_critics: int = 1,
        layer_norm: bool = False,
    ):
        super().__init__(
            observation_space,
            action_space,
            features_extractor_class or self.default_features_extractor_class,
            features_extractor_kwargs,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            squash_output=True,
            normalize_images=normalize_images,
        )
        n_actor_heads, n_critic_heads = check_head_counts(n_actor_heads, n_critic_heads)
        if not (isinstance(activation_fn, type) and issubclass(activation_fn, nn.Module)):
            raise ValueError(
                f"activation_fn must be an nn.Module class such as nn.LeakyReLU (the class, not an instance), "
                f"got {activation_fn!r}"
            )
        self.net_arch = parse_net_arch(net_arch)
        check_n_critics(n_critics, n_critic_heads)
        self.activation_fn = activation_fn
        self.n_actor_heads = n_actor_heads
        self.n_critic_heads = n_critic_heads
        self.confidence_spec = check_confidence(confidence)
        self.confidence_kwargs = confidence_kwargs  # checked by make_confidence, with the strategy's own arguments
        self.share_features_extractor = share_features_extractor
        self.layer_norm = boolean("LayerNorms in the critic's body")("layer_norm", layer_norm)
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        self.actor = self.make_actor()
        self.actor_target = self.make_actor()
        self.actor_target.load_state_dict(self.actor.state_dict())
        if self.share_features_extractor:
            # as SB3's TD3: the critic target reads the actor target's extractor, which the actor's soft update moves
            self.critic = self.make_critic(self.actor.features_extractor)
            self.critic_target = self.make_critic(self.actor_target.features_extractor)
        else:
            self.critic = self.make_critic()
            self.critic_target = self.make_critic()
        self.critic_target.load_state_dict(self.critic.state_dict())
        for model, target in ((self.actor, self.actor_target), (self.critic, self.critic_target)):
            model.optimizer = self.optimizer_class(  # type: ignore[call-arg]
                ensemble_param_groups(model.body_parameters(), model.head_parameters()),
                lr=lr_schedule(1),
                **self.optimizer_kwargs,
            )
            target.set_training_mode(False)
            target.requires_grad_(False)
        self.confidence = make_confidence(self.confidence_spec, self.confidence_kwargs)
        self.confidence.setup(self)

    def make_actor(self) -> EnsembleActor:
        """:return: a new actor with its own features extractor"""
        actor = EnsembleActor(**self._network_arguments("pi", self.n_actor_heads, self.make_features_extractor()))
        return actor.to(self.device)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> EnsembleCritic:
        """
        :param features_extractor: the actor's features extractor, to share (None: a new one of its own)
        :return: a new critic
        """
        extractor = self.make_features_extractor() if features_extractor is None else features_extractor
        return EnsembleCritic(
            **self._network_arguments("qf", self.n_critic_heads, extractor),
            share_features_extractor=features_extractor is not None,
            action_layer=self.net_arch["qf_action_layer"],
            layer_norm=self.layer_norm,
        ).to(self.device)

    def _network_arguments(self, kind: str, n_heads: int, extractor: BaseFeaturesExtractor) -> dict[str, Any]:
        """The arguments an ensemble network ("pi": the actor, "qf": the critic) shares with the other."""
        return dict(
            observation_space=self.observation_space,
            action_space=self.action_space,
            n_heads=n_heads,
            body_arch=self.net_arch[f"{kind}_body"],
            head_arch=self.net_arch[f"{kind}_head"],
            features_extractor=extractor,
            features_dim=extractor.features_dim,
            activation_fn=self.activation_fn,
            normalize_images=self.normalize_images,
        )

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                net_arch=self.net_arch,
                activation_fn=self.activation_fn,
                n_actor_heads=self.n_actor_heads,
                n_critic_heads=self.n_critic_heads,
                confidence=self.confidence_spec,
                confidence_kwargs=self.confidence_kwargs,
                lr_schedule=self._dummy_schedule,  # dummy lr schedule, not needed for loading policy alone
                optimizer_class=self.optimizer_class,
                optimizer_kwargs=self.optimizer_kwargs,
                features_extractor_class=self.features_extractor_class,
                features_extractor_kwargs=self.features_extractor_kwargs,
                share_features_extractor=self.share_features_extractor,
                layer_norm=self.layer_norm,
            )
        )
        return data

    @property
    def n_pairs(self) -> int:
        """Number of (actor head, critic head) pairs, i.e. of bootstrap masks: max(n_actor_heads, n_critic_heads)."""
        return max(self.n_actor_heads, self.n_critic_heads)

    def actor_heads(self, pairs: list[int]) -> TrainedHeads:
        """The actor heads of head pairs ``pairs`` (actor head k is in pair k; a single head serves every pair)."""
        return self._trained_heads(pairs, self.n_actor_heads)

    def critic_heads(self, pairs: list[int]) -> TrainedHeads:
        """The critic heads of head pairs ``pairs`` (critic head k is in pair k; a single head serves every pair)."""
        return self._trained_heads(pairs, self.n_critic_heads)

    def _trained_heads(self, pairs: list[int], n_heads: int) -> TrainedHeads:
        per_pair = list(pairs) if n_heads > 1 else [0] * len(pairs)
        distinct = sorted(set(per_pair))
        head_arg: HeadIndex = None
        if len(pairs) == 1:
            head_arg = per_pair[0]  # one pair: the network's plain (B, ...) single-head pass
        elif n_heads > 1 and per_pair != list(range(n_heads)):
            head_arg = th.as_tensor(per_pair, device=self.device)
        rows: int | th.Tensor | None = None
        if len(distinct) == 1 and n_heads > 1:
            rows = distinct[0]
        elif len(distinct) < n_heads:
            rows = th.zeros(n_heads, dtype=th.bool, device=self.device)
            rows[distinct] = True
        return TrainedHeads(per_pair, head_arg, rows)

    def describe_pairs(self, pairs: list[int], per_pair_values: th.Tensor) -> str:
        """
        :param pairs: head pairs
        :param per_pair_values: a value per pair (e.g. losses)
        :return: the pairs whose value is not finite (all of them when each is), with their actor and critic heads
        """
        finite = th.isfinite(per_pair_values.detach().reshape(len(pairs), -1)).all(dim=1).tolist()
        bad = [pair for pair, ok in zip(pairs, finite) if not ok] or pairs
        actor, critic = self.actor_heads(bad).per_pair, self.critic_heads(bad).per_pair
        return f"head pair(s) {bad} (actor head(s) {actor}, critic head(s) {critic})"

    def select(self, obs: PyTorchObs, explore: bool = False) -> Selection:
        """
        Ensemble action selection (eq. 7), batched over observations, without noise.
        Every actor head proposes a candidate, every critic head scores every candidate (``V``),
        the confidence strategy weights the scores (``W``), and the best E-Q value wins.

        :param explore: weight with the strategy's ``exploration_weights`` (acting during ``learn``) instead of its
            ``weights`` (greedy actions)
        """
        candidates = self.actor(obs)  # (Ka, B, A)
        if self.n_actor_heads == 1 and self.n_critic_heads == 1:
            chosen = th.zeros(candidates.shape[1], dtype=th.long, device=candidates.device)
            return Selection(candidates[0], chosen, None, None, candidates)
        q_matrix = self.critic.q_matrix(obs, candidates)  # (B, Kc, Ka)
        strategy = self.confidence
        weights = (strategy.exploration_weights if explore else strategy.weights)(obs, q_matrix)  # broadcastable to V
        check_weights(self.confidence, weights, q_matrix)
        actions, chosen = e_actor(candidates, e_critic(q_matrix, weights))
        return Selection(actions, chosen, q_matrix, weights, candidates)

    def ensemble_view(self, observation: np.ndarray | dict[str, np.ndarray], explore: bool = False) -> EnsembleView:
        """
        What the whole ensemble thinks of a batch of observations: every actor head's candidate, every critic head's
        value of every candidate, the confidence weights, the chosen head and how much the critic heads disagree on
        the chosen action (``q_spread``): the ensemble's uncertainty, for safe exploration, monitoring or active
        learning. It changes nothing: ``predict`` returns what it returned before, and ``actions`` is its deterministic
        action.

        ``V`` and ``W`` are computed whatever the head counts (with one actor and one critic head, which ``predict``
        does not score, ``V`` is ``(B, 1, 1)`` and ``W`` ones).

        :param observation: observations as ``predict`` takes them (NumPy, a dict of them for Dict spaces, batched or
            not, channel-last images transposed); with a ``VecNormalize`` env, normalise them first
            (``env.normalize_obs``), as for ``predict``
        :param explore: weight with the strategy's ``exploration_weights`` (what ``learn`` acts on, e.g. UCB's
            optimistic bonus) instead of its ``weights`` (greedy actions); ``actions`` is then the noise-free action
            ``learn`` would take
        :return: NumPy arrays (see :class:`EnsembleView`), without the batch dimension for an unbatched observation
        """
        self.set_training_mode(False)
        obs, vectorized = self.obs_to_tensor(observation)
        with th.no_grad():
            selection = self.select(obs, explore=explore)  # what predict (explore=False) and learn (True) act on
            candidates, chosen = selection.candidates, selection.chosen  # (Ka, B, A), (B,)
            assert candidates is not None
            if selection.q_matrix is None or selection.weights is None:  # one candidate, which select() does not score
                q_matrix = self.critic.q_matrix(obs, candidates)  # (B, 1, 1)
                weights = th.ones_like(q_matrix)
            else:
                q_matrix, weights = selection.q_matrix, selection.weights.expand_as(selection.q_matrix)  # (B, Kc, Ka)
            e_q = e_critic(q_matrix, weights)  # (B, Ka)
            chosen_q = q_matrix[th.arange(len(chosen), device=chosen.device), :, chosen]  # (B, Kc)
            q_spread = chosen_q.std(dim=1) if self.n_critic_heads > 1 else th.zeros_like(chosen_q[:, 0])  # (B,)
            values = (
                selection.actions,
                candidates.transpose(0, 1),
                q_matrix,
                weights,
                e_q,
                chosen,
                chosen_q.mean(dim=1),
                q_spread,
            )
        arrays = [value.cpu().numpy() for value in values]
        action_shape = self.action_space.shape
        assert action_shape is not None
        for i in (0, 1):  # the actions in the env's bounds, shaped as the action space
            arrays[i] = self.unscale_action(arrays[i].reshape((*arrays[i].shape[:-1], *action_shape)))
        if not vectorized:
            arrays = [array.squeeze(axis=0) for array in arrays]
        return EnsembleView(*arrays)

    def forward(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(observation, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        # no noise (as TD3's): the algorithm adds its action_noise while learning
        return self.select(observation, explore=not deterministic).actions  # (B, A) in [-1, 1]

    def set_training_mode(self, mode: bool) -> None:
        """
        Put the policy in either training or evaluation mode (affects batch norm / dropout).
        The target networks stay in evaluation mode.

        :param mode: if true, set to training mode, else set to evaluation mode
        """
        if self.training == mode and all(module.training == mode for module in (self.actor, self.critic, self.confidence)):
            return  # already there (called before every gradient step: skip walking the module trees)
        self.actor.set_training_mode(mode)
        self.critic.set_training_mode(mode)
        self.confidence.train(mode)
        self.training = mode


MlpPolicy = SOUPPolicy


class CnnPolicy(SOUPPolicy):
    """
    Policy class for SOUP with image observations (see :class:`SOUPPolicy` for the parameters), as SB3's TD3
    ``CnnPolicy``: SB3's ``NatureCNN`` by default, images scaled to [0, 1] (``normalize_images``), channel-last images
    transposed by SB3 (``VecTransposeImage``), one extractor per network unless ``share_features_extractor=True``.
    """

    default_features_extractor_class = NatureCNN


class MultiInputPolicy(SOUPPolicy):
    """
    Policy class for SOUP with Dict observations (see :class:`SOUPPolicy` for the parameters);
    uses SB3's ``CombinedExtractor`` by default (a ``NatureCNN`` for each image key, flattened other keys).
    """

    default_features_extractor_class = CombinedExtractor
