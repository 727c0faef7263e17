"""
The fused fast paths (issue 5) give the numbers of the straightforward computations they replace:
batched ensemble layers, the critic's fused action projection, EnsembleAdam's fused update, cached parameter lists.
"""

import copy

import pytest
import torch as th
from torch import nn
from torch.nn import functional as F

from sb3_soup import SOUP
from sb3_soup.networks import VectorizedLinear
from sb3_soup.optim import EnsembleAdam, ensemble_param_groups


def reference_layer(layer: VectorizedLinear, x: th.Tensor) -> th.Tensor:
    """One nn.Linear-style product per head, stacked."""
    if x.dim() == 2:
        x = x.unsqueeze(0).expand(layer.n_heads, -1, -1)
    n = max(x.shape[0], layer.n_heads)
    x = x.expand(n, -1, -1)
    weight, bias = layer.weight.expand(n, -1, -1), layer.bias.expand(n, -1, -1)
    return th.stack([x[k] @ weight[k] + bias[k] for k in range(n)])  # (K, B, out)


@pytest.mark.parametrize("n_heads, x_shape", [(4, (6, 5)), (4, (4, 6, 5)), (4, (1, 6, 5)), (1, (3, 6, 5))])
def test_vectorized_linear_matches_per_head_products(n_heads, x_shape):
    th.manual_seed(0)
    layer = VectorizedLinear(5, 7, n_heads)
    x = th.randn(*x_shape, requires_grad=True)
    out = layer(x)
    x_ref = x.detach().clone().requires_grad_(True)
    ref_layer = copy.deepcopy(layer)
    ref = reference_layer(ref_layer, x_ref)
    assert out.shape == ref.shape
    th.testing.assert_close(out, ref)
    # same gradients for the input (summed over the heads when shared), the weights and the biases
    grad = th.randn_like(out)
    out.backward(grad)
    ref.backward(grad)
    th.testing.assert_close(x.grad, x_ref.grad)
    th.testing.assert_close(layer.weight.grad, ref_layer.weight.grad)
    th.testing.assert_close(layer.bias.grad, ref_layer.bias.grad)


def test_vectorized_linear_one_head():
    th.manual_seed(0)
    layer = VectorizedLinear(5, 7, 3)
    x = th.randn(6, 5)
    th.testing.assert_close(layer(x, head=2), x @ layer.weight[2] + layer.bias[2])
    th.testing.assert_close(layer(x, head=2), layer(x)[2])


@pytest.fixture(scope="module")
def model():
    return SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, buffer_size=100, learning_starts=10, seed=0)


@pytest.mark.parametrize("action_layer", [0, 1], ids=["input", "second-layer"])
@pytest.mark.parametrize("actions_shape", [(8, 1), (3, 8, 1), (1, 8, 1)])
def test_critic_fused_action_projection_matches_concatenation(actions_shape, action_layer):
    """``W [h1; a] + b`` computed on the concatenation, as nn.Linear would, for one or N actions per observation."""
    policy_kwargs = dict(net_arch=dict(qf_action_layer=action_layer))
    critic = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, buffer_size=100, policy_kwargs=policy_kwargs, seed=0).critic
    th.manual_seed(1)
    obs = th.randn(8, 3)
    actions = th.rand(*actions_shape) * 2 - 1

    def first(obs):  # what the layer the action joins takes from the observation: (B, F) or (B, H1)
        return obs if critic.obs_layer is None else critic.activation(critic.obs_layer(obs))

    h1 = first(obs)
    if actions.dim() == 2:
        z = critic.joint_layer(th.cat([h1, actions], dim=-1))
    else:
        z = critic.joint_layer(th.cat([h1.expand(actions.shape[0], -1, -1), actions], dim=-1))
    reference = critic.body(critic.activation(z))
    th.testing.assert_close(critic.body_features(obs, actions), reference)
    # and the gradient w.r.t. the actions (the actor loss), through the strided joint weight
    actions_a = actions.clone().requires_grad_(True)
    actions_b = actions.clone().requires_grad_(True)
    critic.body_features(obs, actions_a).sum().backward()
    h1 = first(obs)
    expanded = h1 if actions.dim() == 2 else h1.expand(actions.shape[0], -1, -1)
    critic.body(critic.activation(critic.joint_layer(th.cat([expanded, actions_b], dim=-1)))).sum().backward()
    th.testing.assert_close(actions_a.grad, actions_b.grad)
    critic.zero_grad(set_to_none=True)


def test_q_matrix_matches_head_by_head_evaluation(model):
    policy = model.policy
    th.manual_seed(2)
    obs = th.randn(5, 3)
    with th.no_grad():
        candidates = policy.actor(obs)  # (Ka, B, A)
        q_matrix = policy.critic.q_matrix(obs, candidates)  # (B, Kc, Ka)
        for i in range(policy.n_critic_heads):
            for k in range(policy.n_actor_heads):
                q = policy.critic(obs, candidates[k], head=i)  # (B, 1)
                th.testing.assert_close(q_matrix[:, i, k], q[:, 0])


def adam_reference_step(optimizer: EnsembleAdam, head) -> None:
    """The per-parameter path, kept for row masks (and for devices without torch's fused Adam)."""
    with th.no_grad():
        for group in optimizer.param_groups:
            rows = head if (group["heads"] and isinstance(head, int)) else ...
            for param in group["params"]:
                if param.grad is not None:
                    optimizer._adam_update(group, param, rows, None)


def make_ensemble_adam(weight_decay: float, **options):
    th.manual_seed(0)
    body = [nn.Parameter(th.randn(5, 3)), nn.Parameter(th.randn(3))]
    heads = [nn.Parameter(th.randn(4, 3, 2)), nn.Parameter(th.randn(4, 1, 2))]
    return body, heads, EnsembleAdam(ensemble_param_groups(body, heads), lr=1e-2, weight_decay=weight_decay, **options)


# torch.optim.Adam's options beside lr, betas, eps and weight_decay, which SB3 passes on from optimizer_kwargs
ADAM_OPTIONS = [{}, dict(amsgrad=True), dict(maximize=True), dict(decoupled_weight_decay=True), dict(fused=False)]


def set_gradients(step: int, *parameter_lists: list[th.Tensor]) -> None:
    th.manual_seed(100 + step)
    grads = [th.randn_like(p) for p in parameter_lists[0]]
    for params in parameter_lists:
        for param, grad in zip(params, grads):
            param.grad = grad.clone()


@pytest.mark.parametrize("options", ADAM_OPTIONS, ids=str)
@pytest.mark.parametrize("weight_decay", [0.0, 0.1])
@pytest.mark.parametrize("head", [None, 0, 2, "mask"])
def test_ensemble_adam_is_one_torch_adam_per_head(weight_decay, head, options):
    """Every head (and the shared body) trained as by its own ``torch.optim.Adam``, as the paper's K optimizers, with
    any of torch Adam's options."""
    body, heads, ensemble = make_ensemble_adam(weight_decay, **options)
    n_heads = heads[0].shape[0]
    # the reference: the body's parameters and each head's rows as separate parameters, one torch Adam each
    body_ref = [nn.Parameter(p.detach().clone()) for p in body]
    heads_ref = [[nn.Parameter(p.detach()[k].clone()) for p in heads] for k in range(n_heads)]
    adam = dict(lr=1e-2, weight_decay=weight_decay, **{"fused": True, **options})
    body_opt = th.optim.Adam(body_ref, **adam)
    head_opts = [th.optim.Adam(params, **adam) for params in heads_ref]
    if head == "mask":  # a row mask: heads 1 and 3
        head = th.tensor([k in (1, 3) for k in range(n_heads)])
    trained = range(n_heads) if head is None else [head] if isinstance(head, int) else head.nonzero()[:, 0].tolist()
    for step in range(5):
        set_gradients(step, body + heads)
        for param, ref in zip(body, body_ref):
            ref.grad = param.grad.clone()
        for k in range(n_heads):
            for param, ref in zip(heads, heads_ref[k]):
                ref.grad = param.grad[k].clone()
        ensemble.step(head=head)
        body_opt.step()
        for k in trained:
            head_opts[k].step()
    # a row mask runs the per-parameter update, which orders the arithmetic its own way: equal to float32's rounding
    same = th.equal if not isinstance(head, th.Tensor) and options.get("fused") is not False else close
    for param, ref in zip(body, body_ref):
        assert same(param, ref)
    for k in range(n_heads):  # the heads left out kept their values
        for param, ref in zip(heads, heads_ref[k]):
            assert same(param[k], ref)
    _, initial, _ = make_ensemble_adam(weight_decay)
    for param, start in zip(heads, initial):
        for k in range(n_heads):
            assert th.equal(param[k], start[k]) == (k not in trained)


def close(a: th.Tensor, b: th.Tensor) -> bool:
    th.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    return True


@pytest.mark.parametrize("options", ADAM_OPTIONS[:4], ids=str)
@pytest.mark.parametrize("weight_decay", [0.0, 0.1])
@pytest.mark.parametrize("head", [None, 0, 2])
def test_ensemble_adam_fused_update_is_the_per_parameter_update(weight_decay, head, options):
    body_a, heads_a, fast = make_ensemble_adam(weight_decay, **options)
    body_b, heads_b, reference = make_ensemble_adam(weight_decay, **options)
    for step in range(5):
        set_gradients(step, body_a + heads_a, body_b + heads_b)
        fast.step(head=head)
        adam_reference_step(reference, head)
    # the same arithmetic, which the fused kernel orders its own way: equal to float32's rounding
    for a, b in zip(body_a + heads_a, body_b + heads_b):
        th.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
        for key in fast.state[a]:
            th.testing.assert_close(fast.state[a][key], reference.state[b][key], rtol=1e-5, atol=1e-8)


def test_cached_parameter_lists_follow_the_model(model):
    actor = copy.deepcopy(model.actor)
    assert actor.all_parameters() == list(actor.parameters())
    body, heads = actor.body_parameters(), actor.head_parameters()
    assert {id(p) for p in body} | {id(p) for p in heads} == {id(p) for p in actor.parameters()}
    assert not {id(p) for p in body} & {id(p) for p in heads}
    # switching the mode (SB3 does it at every rollout and update) keeps the cache
    lists = actor._parameter_lists
    actor.train(False)
    actor.train(True)
    assert actor._parameter_lists is lists
    # a new submodule invalidates it
    actor.body = nn.Sequential(nn.Linear(3, 256), nn.LeakyReLU())
    assert actor.all_parameters() == list(actor.parameters())
    actor.double()
    assert all(p.dtype == th.float64 for p in actor.all_parameters())
    assert actor.all_parameters() == list(actor.parameters())


def test_set_training_mode_still_switches(model):
    policy = model.policy
    policy.set_training_mode(False)
    assert not policy.actor.training and not policy.critic.training
    policy.set_training_mode(True)
    assert policy.actor.training and policy.critic.training and policy.actor.body.training
    policy.actor.eval()  # changed behind the policy's back: still switched back
    policy.set_training_mode(True)
    assert policy.actor.training
    policy.set_training_mode(False)


def test_fused_linear_is_functional_linear():
    # the split of the joint layer used by the critic is nn.Linear on the concatenation
    th.manual_seed(3)
    layer = nn.Linear(6, 4)
    h, a = th.randn(5, 4), th.randn(5, 2)
    w_obs, w_act = layer.weight.split([4, 2], dim=1)
    th.testing.assert_close(th.addmm(F.linear(h, w_obs, layer.bias), a, w_act.T), layer(th.cat([h, a], dim=1)))


def test_ensemble_adam_loads_a_state_saved_before_it_took_torch_adams_options():
    body_a, heads_a, saved = make_ensemble_adam(0.1)
    body_b, heads_b, resumed = make_ensemble_adam(0.1)
    set_gradients(0, body_a + heads_a, body_b + heads_b)
    saved.step(head=1)
    resumed.step(head=1)
    old = resumed.state_dict()
    for group in old["param_groups"]:  # what EnsembleAdam's groups held before
        for key in ("amsgrad", "foreach", "maximize", "fused", "decoupled_weight_decay"):
            del group[key]
    resumed.load_state_dict(old)
    assert resumed.param_groups[0]["amsgrad"] is False and resumed.param_groups[0]["fused"] is None
    set_gradients(1, body_a + heads_a, body_b + heads_b)
    saved.step(head=2)
    resumed.step(head=2)
    for a, b in zip(body_a + heads_a, body_b + heads_b):
        assert th.equal(a, b)
