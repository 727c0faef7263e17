"""
Multi-head networks of SOUP: a shared body followed by K heads whose parameters are batched as (K, in, out) tensors.

Shapes in comments: K heads, B batch, F features, A action dimension, P paired heads (actor head k with critic head k).
"""

import math
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn
from torch.nn import functional as F

HeadIndex = int | th.Tensor | None
"""
Which head(s) to run: an int runs that head alone (output ``(B, out)``), a tensor of H head indices runs those heads
(output ``(H, B, out)``, an index may repeat), ``None`` runs all K heads at once (output ``(K, B, out)``).
"""


class VectorizedLinear(nn.Module):
    """
    K independent linear layers evaluated with one batched matmul (as CORL's ``VectorizedLinear``).
    Each head is initialised independently like ``nn.Linear`` (the ensemble's only source of initial diversity).

    :param in_features: input size
    :param out_features: output size
    :param n_heads: number of heads K
    """

    def __init__(self, in_features: int, out_features: int, n_heads: int):
        super().__init__()
        self.in_features = in_features
        self.out_features = out_features
        self.n_heads = n_heads
        self.weight = nn.Parameter(th.empty(n_heads, in_features, out_features))  # (K, in, out)
        self.bias = nn.Parameter(th.empty(n_heads, 1, out_features))  # (K, 1, out)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        # Same distribution as nn.Linear, drawn independently for every head
        for k in range(self.n_heads):
            nn.init.kaiming_uniform_(self.weight[k].T, a=math.sqrt(5))
        bound = 1 / math.sqrt(self.in_features)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: th.Tensor, head: HeadIndex = None) -> th.Tensor:
        """
        :param x: ``(B, in)`` input shared by the heads, or ``(H or 1, B, in)`` one input per head run
        :param head: which heads to run (see :data:`HeadIndex`); with an int, ``x`` is ``(B, in)``
        :return: ``(K, B, out)`` for all heads, ``(H, B, out)`` for H indexed heads, ``(B, out)`` for one head
        """
        if isinstance(head, int):
            return th.addmm(self.bias[head], x, self.weight[head])  # (B, out)
        weight, bias = (self.weight, self.bias) if head is None else (self.weight[head], self.bias[head])  # (H, in, out)
        if x.dim() == 2:
            x = x.unsqueeze(0)  # (1, B, in), broadcast over the heads
        n_heads = max(x.shape[0], weight.shape[0])
        # One fused batched matmul + bias. An input shared by the heads is expanded (a view, no copy): cheaper than
        # th.matmul's broadcasting, which copies it, and than a separate bias addition on the (K, B, out) output
        return th.baddbmm(bias, x.expand(n_heads, -1, -1), weight.expand(n_heads, -1, -1))  # (K, B, out)

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, out_features={self.out_features}, n_heads={self.n_heads}"


class HeadStack(nn.Module):
    """
    The K heads of an ensemble: ``len(layer_sizes)`` hidden vectorized layers with activation, then a vectorized
    output layer (no activation).

    :param in_features: input size
    :param layer_sizes: hidden sizes of each head
    :param out_features: output size of each head
    :param n_heads: number of heads K
    :param activation_fn: activation after each hidden layer
    """

    def __init__(
        self, in_features: int, layer_sizes: list[int], out_features: int, n_heads: int, activation_fn: type[nn.Module]
    ):
        super().__init__()
        sizes = [in_features, *layer_sizes, out_features]
        self.layers = nn.ModuleList(VectorizedLinear(sizes[i], sizes[i + 1], n_heads) for i in range(len(sizes) - 1))
        self.activation = activation_fn()
        self.n_heads = n_heads

    def forward(self, x: th.Tensor, head: HeadIndex = None) -> th.Tensor:
        for i, layer in enumerate(self.layers):
            x = layer(x, head)
            if i < len(self.layers) - 1:
                x = self.activation(x)
        return x


def mlp(sizes: list[int], activation_fn: type[nn.Module], layer_norm: bool = False) -> nn.Sequential:
    """Linear layers of the given sizes, each followed by the activation (with ``layer_norm``: LayerNorm, then it)."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers += [nn.Linear(sizes[i], sizes[i + 1]), *([nn.LayerNorm(sizes[i + 1])] if layer_norm else []), activation_fn()]
    return nn.Sequential(*layers)


class EnsembleModel(BaseModel):
    """Common part of the multi-head actor and critic: body/head parameter lists for optimizers and soft updates."""

    body: nn.Module
    heads: HeadStack
    # (all, body, head) parameter lists, worked out once: every gradient step and soft update needs them
    _parameter_lists: tuple[list[th.Tensor], list[th.Tensor], list[th.Tensor]] | None = None

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        n_heads: int,
        body_arch: list[int],
        head_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module],
        normalize_images: bool,
    ):
        super().__init__(
            observation_space, action_space, features_extractor=features_extractor, normalize_images=normalize_images
        )
        self.n_heads = n_heads
        self.body_arch = body_arch
        self.head_arch = head_arch
        self.features_dim = features_dim
        self.activation_fn = activation_fn

    def _get_constructor_parameters(self) -> dict:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                n_heads=self.n_heads,
                body_arch=self.body_arch,
                head_arch=self.head_arch,
                features_dim=self.features_dim,
                activation_fn=self.activation_fn,
                features_extractor=self.features_extractor,
            )
        )
        return data

    def _split_parameters(self) -> tuple[list[th.Tensor], list[th.Tensor], list[th.Tensor]]:
        lists = self._parameter_lists
        if lists is None:
            heads: list[th.Tensor] = list(self.heads.parameters())
            head_ids = {id(p) for p in heads}
            every: list[th.Tensor] = list(self.parameters())
            if getattr(self, "share_features_extractor", False):
                # another network's features extractor, trained and soft-updated with that network: not this one's
                shared = {id(p) for p in self.features_extractor.parameters()}  # type: ignore[union-attr]
                every = [p for p in every if id(p) not in shared]
            lists = self._parameter_lists = (every, [p for p in every if id(p) not in head_ids], heads)
        return lists

    def _apply(self, fn, recurse=True):  # type: ignore[no-untyped-def]
        self._parameter_lists = None  # .to(), .float()... may replace the parameters
        return super()._apply(fn, recurse)

    def __setattr__(self, name: str, value: Any) -> None:
        if isinstance(value, (nn.Module, nn.Parameter)) or (
            value is None and (name in self.__dict__.get("_modules", {}) or name in self.__dict__.get("_parameters", {}))
        ):
            self.__dict__["_parameter_lists"] = None  # a new (or removed) submodule or parameter; not e.g. `training`
        super().__setattr__(name, value)

    def all_parameters(self) -> list[th.Tensor]:
        """
        Every parameter this network trains (as ``list(self.parameters())``, cached), without a features extractor shared
        with another network.
        """
        return self._split_parameters()[0]

    def head_parameters(self) -> list[th.Tensor]:
        """Parameters batched over heads, shape (K, ...)."""
        return self._split_parameters()[2]

    def body_parameters(self) -> list[th.Tensor]:
        """Parameters shared by all heads (features extractor, unless shared with another network, and body)."""
        return self._split_parameters()[1]


class EnsembleActor(EnsembleModel):
    """
    Bootstrapped actor: shared body [256] -> K heads [128] -> tanh (paper sizes by default).
    Outputs are in [-1, 1]; the policy rescales them to the action bounds.

    :param observation_space: observation space
    :param action_space: action space (Box)
    :param n_heads: number of actor heads
    :param body_arch: hidden sizes of the shared body
    :param head_arch: hidden sizes of each head
    :param features_extractor: features extractor (SB3)
    :param features_dim: its output size
    :param activation_fn: activation function
    :param normalize_images: whether to divide images by 255
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        n_heads: int,
        body_arch: list[int],
        head_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.LeakyReLU,
        normalize_images: bool = True,
    ):
        super().__init__(
            observation_space, action_space, n_heads, body_arch, head_arch, features_extractor, features_dim, activation_fn,
            normalize_images,
        )  # fmt: skip
        self.body = mlp([features_dim, *body_arch], activation_fn)
        body_out = body_arch[-1] if body_arch else features_dim
        self.heads = HeadStack(body_out, head_arch, get_action_dim(action_space), n_heads, activation_fn)

    def body_features(self, obs: PyTorchObs) -> th.Tensor:
        """Shared body output ``(B, F)``."""
        features = self.extract_features(obs, self.features_extractor)  # type: ignore[arg-type]
        return self.body(features)

    def forward(self, obs: PyTorchObs, head: HeadIndex = None) -> th.Tensor:  # type: ignore[override]
        """
        :return: candidates ``(K, B, A)`` of all heads, or ``(B, A)`` of one head
        """
        return th.tanh(self.heads(self.body_features(obs), head))


class EnsembleCritic(EnsembleModel):
    """
    Bootstrapped critic: shared body [256, 256] where the action joins at the second layer (as in DDPG),
    then K heads [128] -> 1 (paper sizes by default). With ``action_layer=0`` the action joins at the input, as in
    SB3's ``ContinuousCritic`` (``Q(s, a) = heads(body([features(s); a]))``); with an empty body the heads take
    ``[features(s); a]``.

    The layer the action joins is split as ``W [h; a] = W_h h + W_a a`` so that scoring K candidates computes the
    observation part once: the K x K matrix ``V[i, k] = Q_i(s, a^k)`` costs one observation pass plus K cheap action
    projections (and, after the joint layer, one pass of the rest of the body per candidate).

    :param observation_space: observation space
    :param action_space: action space (Box)
    :param n_heads: number of critic heads
    :param body_arch: hidden sizes of the shared body (at least two when the action joins at the second)
    :param head_arch: hidden sizes of each head
    :param features_extractor: features extractor (SB3)
    :param features_dim: its output size
    :param activation_fn: activation function
    :param normalize_images: whether to divide images by 255
    :param share_features_extractor: ``features_extractor`` is the actor's (as SB3's ``ContinuousCritic``): the critic
        reads its features without gradient, and neither trains it nor soft-updates it (the actor does)
    :param action_layer: the body layer whose input the action joins: 1, the second (the paper's DDPG critic), or 0,
        the first (SB3's critic)
    :param layer_norm: a LayerNorm after each linear layer of the body, before its activation (the heads have none)
    """

    obs_layer: nn.Linear | None
    joint_layer: nn.Linear | None

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        n_heads: int,
        body_arch: list[int],
        head_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.LeakyReLU,
        normalize_images: bool = True,
        share_features_extractor: bool = False,
        action_layer: int = 1,
        layer_norm: bool = False,
    ):
        super().__init__(
            observation_space, action_space, n_heads, body_arch, head_arch, features_extractor, features_dim, activation_fn,
            normalize_images,
        )  # fmt: skip
        self.share_features_extractor = share_features_extractor
        if action_layer not in (0, 1):
            raise ValueError(
                f"net_arch['qf_action_layer'] must be 0 (the action joins the critic's input, as in SB3) or 1 (at the "
                f"second layer, the paper's DDPG critic), got {action_layer!r}"
            )
        if action_layer == 1 and len(body_arch) < 2:
            raise ValueError(
                f"net_arch['qf_body'] needs at least 2 layers (the action joins at the second), got {body_arch}; "
                "with net_arch['qf_action_layer']=0 the action joins at the input (SB3's critic) and any body goes"
            )
        if layer_norm and not body_arch:
            raise ValueError(
                "layer_norm=True puts a LayerNorm after each layer of the critic's shared body, and net_arch gives it none "
                "(qf_body=[]; in SB3's list form the last layer is each head's, the others the body): give the critic a "
                "body (e.g. net_arch=[256, 256, 128]) or leave layer_norm out"
            )
        self.action_layer = action_layer
        self.layer_norm = layer_norm
        action_dim = get_action_dim(action_space)
        if action_layer == 1:
            self.obs_layer = nn.Linear(features_dim, body_arch[0])  # (F -> H1)
            self.joint_layer = nn.Linear(body_arch[0] + action_dim, body_arch[1])  # ([H1, A] -> H2)
            self.body = mlp(body_arch[1:], activation_fn, layer_norm)  # remaining body layers (empty for [H1, H2])
        else:
            self.obs_layer = None
            # ([F, A] -> H1), or no body: the heads take [F, A]
            self.joint_layer = nn.Linear(features_dim + action_dim, body_arch[0]) if body_arch else None
            self.body = mlp(body_arch, activation_fn, layer_norm)  # remaining body layers
        # the LayerNorms of the observation and the joint layers (identities without layer_norm: no parameters)
        self.obs_norm = nn.LayerNorm(body_arch[0]) if layer_norm and self.obs_layer is not None else nn.Identity()
        self.joint_norm = nn.LayerNorm(self.joint_layer.out_features) if layer_norm and self.joint_layer else nn.Identity()
        self.activation = activation_fn()
        self.heads = HeadStack(body_arch[-1] if body_arch else features_dim + action_dim, head_arch, 1, n_heads, activation_fn)

    def _get_constructor_parameters(self) -> dict:
        data = super()._get_constructor_parameters()
        data.update(
            share_features_extractor=self.share_features_extractor, action_layer=self.action_layer, layer_norm=self.layer_norm
        )
        return data

    def body_features(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """
        :param actions: ``(B, A)`` or ``(N, B, A)`` (N candidate actions per observation)
        :return: body output ``(B, F)`` or ``(N, B, F)``
        """
        if self.share_features_extractor:
            with th.no_grad():  # the actor's extractor, trained by the actor's loss only (as in SB3)
                features = self.extract_features(obs, self.features_extractor)  # type: ignore[arg-type]
        else:
            features = self.extract_features(obs, self.features_extractor)  # type: ignore[arg-type]
        h1 = features if self.obs_layer is None else self.activation(self.obs_norm(self.obs_layer(features)))  # (B, H1)/(B, F)
        if self.joint_layer is None:  # no body: the heads take [features; action]
            if actions.dim() == 3:
                h1 = h1.expand(actions.shape[0], -1, -1)  # (N, B, F)
            return th.cat([h1, actions], dim=-1)
        w_obs, w_act = self.joint_layer.weight.split([h1.shape[-1], actions.shape[-1]], dim=1)
        z_obs = F.linear(h1, w_obs, self.joint_layer.bias)  # (B, H2)
        # the action projection is fused with the addition of the observation part (one op, one output tensor)
        if actions.dim() == 2:
            z = th.addmm(z_obs, actions, w_act.T)  # (B, H2)
        else:
            # (A, H2) made contiguous (a tiny copy) so that the backward's gradient w.r.t. the actions, (N, B, H2) x
            # (H2, A), reads it transposed: 4x faster than the strided slice of the joint weight
            w_act_t = w_act.T.contiguous()  # (A, H2)
            z = th.baddbmm(z_obs.unsqueeze(0), actions, w_act_t.expand(actions.shape[0], -1, -1))  # (N, B, H2)
        return self.body(self.activation(self.joint_norm(z)))

    def forward(self, obs: PyTorchObs, actions: th.Tensor, head: HeadIndex = None) -> th.Tensor:  # type: ignore[override]
        """
        Q-values of (obs, actions).

        - ``head=k``, actions ``(B, A)``: head k only, returns ``(B, 1)``;
        - ``head=None``, actions ``(B, A)``: every head on the same actions, returns ``(K, B, 1)``;
        - ``head=None``, actions ``(K or 1, B, A)``: head k scores actions[k] (broadcast when one side is 1),
          returns ``(P, B, 1)``: the paired evaluation used to train all heads at once;
        - ``head=idx`` (H indices), actions ``(B, A)`` or ``(H or 1, B, A)``: head ``idx[h]`` scores actions[h],
          returns ``(H, B, 1)``.
        """
        return self.heads(self.body_features(obs, actions), head)

    def q_matrix(self, obs: PyTorchObs, candidates: th.Tensor) -> th.Tensor:
        """
        E-Critic input: every critic head scores every candidate.

        :param candidates: ``(Ka, B, A)`` actions proposed by the actor heads
        :return: ``V`` of shape ``(B, Kc, Ka)`` with ``V[b, i, k] = Q_i(s_b, a_b^k)``
        """
        n_candidates, batch_size, _ = candidates.shape
        features = self.body_features(obs, candidates)  # (Ka, B, F)
        q = self.heads(features.reshape(1, n_candidates * batch_size, -1))  # (Kc, Ka * B, 1)
        return q.reshape(self.n_heads, n_candidates, batch_size).permute(2, 0, 1)  # (B, Kc, Ka)


def soft_update(model: EnsembleModel, target: EnsembleModel, tau: float, head: int | th.Tensor | None = None) -> None:
    """
    Polyak update (eq. 6) of the shared body and of the heads trained: one (``head=k``), those of a (K,) bool mask, or
    every head (``head=None``). Buffers (e.g. batch-norm statistics) are copied.
    """
    with th.no_grad():
        if model.body_parameters():  # none for a linear body over a parameter-free extractor (net_arch [] or [64])
            th._foreach_lerp_(target.body_parameters(), model.body_parameters(), tau)
        if head is None:
            th._foreach_lerp_(target.head_parameters(), model.head_parameters(), tau)
        else:
            rows = [head] if isinstance(head, int) else th.nonzero(head).flatten().tolist()
            for row in rows:
                th._foreach_lerp_([p[row] for p in target.head_parameters()], [p[row] for p in model.head_parameters()], tau)
        for target_buffer, buffer in zip(target.buffers(), model.buffers()):
            target_buffer.copy_(buffer)
