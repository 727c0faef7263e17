"""
ONNX export of SOUP's deterministic E-action policy, following SB3's "Exporting models" guide (an ``nn.Module`` that
wraps the policy, exported with ``torch.onnx.export``, checked with ``onnx`` and run with ``onnxruntime``), for
deployment without Python or PyTorch.

The graph holds the whole ensemble decision of ``model.predict(obs, deterministic=True)``: the observation's
preprocessing (images scaled to [0, 1]), every actor head's candidate, the K x K critic scoring ``V``, the confidence
weights ``W``, the E-Q values, their argmax (eq. 7) and the rescaling of the chosen action to the action space's bounds.

Recipe (``pip install "sb3-soup[onnx]"``)::

    import numpy as np
    import onnxruntime as ort
    from sb3_soup import SOUP, export_onnx

    model = SOUP.load("soup_pendulum.zip")
    export_onnx(model, "soup_pendulum.onnx")

    session = ort.InferenceSession("soup_pendulum.onnx", providers=["CPUExecutionProvider"])
    obs = np.zeros((4, *model.observation_space.shape), dtype=np.float32)  # a batch of 4 observations
    (actions,) = session.run(None, {"obs": obs})  # (4, *action_shape), as model.predict(obs, deterministic=True)[0]

What stays outside the graph, as in SB3's guide:

- observations are batched, of the policy's observation space: for images that SB3 transposed (channel-last envs are
  wrapped in ``VecTransposeImage``), pass them channel-first (``np.transpose(obs, (0, 3, 1, 2))``); with
  ``VecNormalize``, normalise them first (``vec_normalize.normalize_obs(obs)``);
- float observations are float32 (as the policy computes, even for a float64 space such as MuJoCo's), images uint8;
- Dict observations are one input per key, named by the key;
- the exploration noise (the exported policy is the deterministic one);
- the confidence weights that depend on neither the observation nor ``V`` (``none``, ``fixed``, ``decayed`` and
  ``ucb``'s greedy weights, the mean of the critic heads) are stored as constants: the decayed confidence's as they are
  at export time. The adaptive confidence network is part of the graph. A custom strategy's ``weights`` is exported as
  it computes them (it must be traceable by ``torch.export``).
"""

from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from torch import nn

from sb3_soup.confidence import DecayedConfidence, FixedConfidence, NoConfidence, UCBConfidence
from sb3_soup.policies import SOUPPolicy, e_actor, e_critic

# The strategies whose W (in predict(deterministic=True)) depends on neither the observation nor V: exported as constants
_CONSTANT_WEIGHTS = (NoConfidence.weights, FixedConfidence.weights, DecayedConfidence.weights, UCBConfidence.weights)


class OnnxableSOUPPolicy(nn.Module):
    """
    The deterministic E-action policy of a :class:`sb3_soup.SOUPPolicy` as one module with tensor inputs and output, to
    export (``torch.onnx.export``) or trace.

    :param policy: the policy (left in evaluation mode)
    """

    low: th.Tensor
    high: th.Tensor
    constant_weights: th.Tensor | None

    def __init__(self, policy: SOUPPolicy):
        super().__init__()
        action_space = policy.action_space
        if not isinstance(action_space, spaces.Box):  # pragma: no cover (SOUP takes Box actions only)
            raise ValueError(f"SOUP's actions are a Box, got {action_space}")
        observation_space = policy.observation_space
        boxes = observation_space.spaces.values() if isinstance(observation_space, spaces.Dict) else [observation_space]
        if not all(isinstance(space, spaces.Box) for space in boxes):
            raise ValueError(f"the ONNX export takes Box observations or a Dict of Box observations, got {observation_space}")
        policy.set_training_mode(False)
        self.policy = policy
        self.keys = list(observation_space.spaces) if isinstance(observation_space, spaces.Dict) else None
        self.action_shape = tuple(action_space.shape)
        for name, bound in (("low", action_space.low), ("high", action_space.high)):  # (A,) each, on the policy's device
            self.register_buffer(name, th.as_tensor(bound, dtype=th.float32, device=policy.device).flatten(), persistent=False)
        self.register_buffer("constant_weights", None, persistent=False)  # (1, Kc, Ka) for a strategy of constant W
        one_candidate = policy.n_actor_heads == 1 and policy.n_critic_heads == 1
        if not one_candidate and getattr(type(policy.confidence), "weights", None) in _CONSTANT_WEIGHTS:
            example = self.example_inputs(batch_size=1)
            with th.no_grad():
                obs = self._observation(example)
                q_matrix = policy.critic.q_matrix(obs, policy.actor(obs))  # (1, Kc, Ka)
                weights = policy.confidence.weights(obs, q_matrix).expand_as(q_matrix)[:1]  # (1, Kc, Ka)
            self.constant_weights = weights.detach().clone()

    @property
    def input_names(self) -> list[str]:
        """The graph's input names: ``["obs"]``, or the Dict observation's keys."""
        return ["obs"] if self.keys is None else list(self.keys)

    def input_dtypes(self) -> list[np.dtype]:
        """
        The graph's input types: float32 for float observations (the policy computes in float32, whatever the space's
        float type, e.g. MuJoCo's float64), the space's type otherwise (uint8 images, scaled in the graph).
        """
        observation_space = self.policy.observation_space
        boxes = [observation_space] if self.keys is None else [observation_space[key] for key in self.keys]  # type: ignore[index]
        return [np.dtype(np.float32) if np.issubdtype(box.dtype, np.floating) else np.dtype(box.dtype) for box in boxes]

    def example_inputs(self, batch_size: int = 2) -> tuple[th.Tensor, ...]:
        """:return: a batch of observations sampled from the observation space, one tensor per input"""
        observation_space = self.policy.observation_space
        boxes = [observation_space] if self.keys is None else [observation_space[key] for key in self.keys]  # type: ignore[index]
        device = self.policy.device
        return tuple(
            th.as_tensor(np.stack([box.sample() for _ in range(batch_size)]).astype(dtype), device=device)
            for box, dtype in zip(boxes, self.input_dtypes())
        )

    def _observation(self, inputs: tuple[th.Tensor, ...]) -> Any:
        return inputs[0] if self.keys is None else dict(zip(self.keys, inputs))

    def forward(self, *inputs: th.Tensor) -> th.Tensor:
        """
        :param inputs: the observations ``(B, *obs_shape)`` (one tensor per key of a Dict observation, in its order)
        :return: the E-actions ``(B, *action_shape)`` in the action space's bounds
        """
        policy, obs = self.policy, self._observation(inputs)
        candidates = policy.actor(obs)  # (Ka, B, A) in [-1, 1]
        if policy.n_actor_heads == 1 and policy.n_critic_heads == 1:
            actions = candidates[0]  # (B, A): one candidate, not scored (as SOUPPolicy.select)
        else:
            q_matrix = policy.critic.q_matrix(obs, candidates)  # (B, Kc, Ka)
            weights = self.constant_weights
            if weights is None:
                weights = policy.confidence.weights(obs, q_matrix)  # broadcastable to (B, Kc, Ka)
            actions, _ = e_actor(candidates, e_critic(q_matrix, weights))  # (B, A)
        actions = self.low + 0.5 * (actions + 1.0) * (self.high - self.low)  # as BasePolicy.unscale_action
        return actions.reshape(-1, *self.action_shape)


def export_onnx(model: Any, path: str | Path, opset_version: int | None = None) -> Path:
    """
    Export the deterministic E-action policy of a SOUP model (or of a :class:`sb3_soup.SOUPPolicy`) to an ONNX file
    (one self-contained file, with a dynamic batch dimension), checked with ``onnx.checker``. The graph computes
    ``model.predict(obs, deterministic=True)[0]`` for a batch of observations: see the module's documentation for its
    inputs, its output and the recipe to run it with ``onnxruntime``.

    Needs the ``onnx`` extra (``pip install "sb3-soup[onnx]"``: onnx, onnxscript for torch's exporter, onnxruntime).

    :param model: a trained ``SOUP`` model, or its policy
    :param path: the ``.onnx`` file to write
    :param opset_version: the ONNX opset (None: torch's default)
    :return: the path written
    """
    try:
        import onnx
        import onnxscript  # noqa: F401 (torch.onnx.export's dynamo exporter needs it)
    except ImportError as error:
        raise ImportError(f"export_onnx needs onnx and onnxscript: pip install 'sb3-soup[onnx]' ({error})") from error
    policy = model if isinstance(model, SOUPPolicy) else getattr(model, "policy", None)
    if not isinstance(policy, SOUPPolicy):
        raise ValueError(f"export_onnx takes a SOUP model or a SOUPPolicy, got {type(model).__name__}")
    onnxable = OnnxableSOUPPolicy(policy).eval()
    names = onnxable.input_names
    batch = th.export.Dim("batch")
    path = Path(path)
    with th.no_grad():
        th.onnx.export(
            onnxable,
            onnxable.example_inputs(batch_size=2),  # 2: a batch of 1 would be taken for a constant
            str(path),
            input_names=names,
            output_names=["actions"],
            opset_version=opset_version,
            dynamic_shapes=(tuple({0: batch} for _ in names),),  # forward(*inputs): one tuple of inputs
            external_data=False,
            verbose=False,
        )
    onnx.checker.check_model(str(path))
    return path
