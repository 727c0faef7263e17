"""``policy_kwargs=dict(layer_norm=True)``: a LayerNorm after each linear layer of the critic's shared body."""

import importlib.util

import numpy as np
import pytest
import torch as th
from torch import nn

from sb3_soup import SOUP, export_onnx

SMALL = dict(n_heads=3, learning_starts=20, batch_size=16, buffer_size=500, seed=0, device="cpu")


def layer_norms(module: nn.Module) -> list[nn.LayerNorm]:
    return [m for m in module.modules() if isinstance(m, nn.LayerNorm)]


def test_layer_norm_is_off_by_default_and_adds_nothing():
    model = SOUP("MlpPolicy", "Pendulum-v1", **SMALL)
    assert model.policy.layer_norm is False and layer_norms(model.policy) == []
    assert not [key for key in model.policy.state_dict() if "norm" in key]  # files saved before it load as they did


@pytest.mark.parametrize(
    "net_arch, body_sizes",
    [
        (None, [256, 256]),  # the paper's critic: observation layer, joint layer (the action joins)
        (dict(qf_body=[32, 32, 16]), [32, 32, 16]),
        ([64, 32], [64]),  # SB3's form: the action joins at the input, the last layer is each head's
    ],
)
def test_layer_norm_follows_every_linear_layer_of_the_critic_body_not_the_heads(net_arch, body_sizes):
    model = SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=net_arch, layer_norm=True), **SMALL)
    for critic in (model.critic, model.critic_target):
        assert sorted(norm.normalized_shape[0] for norm in layer_norms(critic)) == sorted(body_sizes)
        assert layer_norms(critic.heads) == []
    assert layer_norms(model.actor) == []
    # every body layer's output is normalised before its activation
    obs = th.as_tensor(np.stack([model.observation_space.sample() for _ in range(8)]))
    captured = []
    hooks = [norm.register_forward_hook(lambda _m, _i, out: captured.append(out)) for norm in layer_norms(model.critic)]
    model.critic(obs, th.zeros(8, 1))
    for hook in hooks:
        hook.remove()
    assert len(captured) == len(body_sizes)
    for out in captured:  # LayerNorm's initial affine is the identity: mean 0, std 1 per sample
        th.testing.assert_close(out.mean(-1), th.zeros(8), atol=1e-5, rtol=0)
        th.testing.assert_close(out.var(-1, unbiased=False), th.ones(8), atol=1e-3, rtol=0)


def test_layer_norm_parameters_are_trained_and_soft_updated_with_the_body():
    model = SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(layer_norm=True), **SMALL)
    model.learn(60)
    for norm, target_norm in zip(layer_norms(model.critic), layer_norms(model.critic_target)):
        assert not th.equal(norm.weight, th.ones_like(norm.weight))  # trained by the critic loss
        assert not th.equal(target_norm.weight, th.ones_like(target_norm.weight))  # followed by the Polyak update
        assert not th.equal(target_norm.weight, norm.weight)


def test_a_layer_norm_model_saves_loads_and_exports(tmp_path):
    model = SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(layer_norm=True), **SMALL).learn(60)
    model.save(tmp_path / "model.zip")
    loaded = SOUP.load(tmp_path / "model.zip")
    assert loaded.policy.layer_norm is True
    model.observation_space.seed(1)
    obs = np.stack([model.observation_space.sample() for _ in range(16)])
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    if importlib.util.find_spec("onnxruntime") is not None:
        import onnxruntime as ort

        graph = ort.InferenceSession(str(export_onnx(model, tmp_path / "policy.onnx")), providers=["CPUExecutionProvider"])
        (actions,) = graph.run(None, {"obs": obs.astype(np.float32)})
        # onnxruntime's tanh rounds differently near saturation (3.5e-5 of an action of bound 2 seen there)
        np.testing.assert_allclose(actions, model.predict(obs, deterministic=True)[0], rtol=0, atol=5e-5)


@pytest.mark.parametrize("net_arch", [[64], [], dict(qf_body=[], qf_action_layer=0)])
def test_layer_norm_without_a_critic_body_is_refused(net_arch):
    with pytest.raises(ValueError, match=r"layer_norm=True puts a LayerNorm after each layer of the critic's shared body"):
        SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=net_arch, layer_norm=True), **SMALL)
    SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=net_arch), **SMALL)  # without it: accepted


def test_layer_norm_must_be_a_bool():
    message = r"layer_norm must be True or False \(LayerNorms in the critic's body\), got 1 \(int\)"
    with pytest.raises(ValueError, match=message):
        SOUP("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(layer_norm=1), **SMALL)
