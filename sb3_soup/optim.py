"""
Adam for ensembles whose heads are batched in one tensor.

Plain Adam moves every parameter that has moments, even one whose gradient is zero, so training head k with
``torch.optim.Adam`` over a (K, in, out) tensor would still move the other heads. ``EnsembleAdam`` keeps Adam's
moments and step count per head (row of dimension 0) for the parameter groups marked ``heads=True`` and, when told
which head is trained, updates that row alone, as K separate optimizers (one per head, as in the paper) would.
"""

from collections.abc import Iterable
from typing import Any

import torch as th
from torch.utils._foreach_utils import _get_fused_kernels_supported_devices

# The devices with torch's fused Adam kernel (``torch._fused_adam_``, which ``torch.optim.Adam(fused=True)`` runs)
FUSED_DEVICES = tuple(_get_fused_kernels_supported_devices())

# torch.optim.Adam's options beside lr, betas, eps and weight_decay, with its defaults (a state saved before
# EnsembleAdam took them trained with these)
ADAM_OPTION_DEFAULTS: dict[str, Any] = dict(
    amsgrad=False, foreach=None, maximize=False, fused=None, decoupled_weight_decay=False
)


class EnsembleAdam(th.optim.Optimizer):
    """
    Adam (Kingma and Ba, 2015) with per-head state for head-batched parameters.

    Parameter groups with ``heads=True`` hold tensors whose first dimension indexes the K heads;
    other groups are ordinary parameters (shared bodies).

    :param params: parameters or parameter groups (dicts with an optional ``heads`` flag)
    :param lr: learning rate
    :param betas: coefficients of the running averages of the gradient and its square
    :param eps: term added to the denominator
    :param weight_decay: L2 penalty (added to the gradient, as ``torch.optim.Adam``; see ``decoupled_weight_decay``)
    :param amsgrad: AMSGrad: divide by the running maximum of the second moment (per head, as ``torch.optim.Adam``)
    :param foreach: accepted for ``torch.optim.Adam``'s signature; torch's choice of kernels, which
        ``EnsembleAdam`` makes itself (``fused``)
    :param maximize: maximise the objective instead of minimising it
    :param capturable: ``False`` only (CUDA-graph capture is not supported)
    :param differentiable: ``False`` only (differentiating through the step is not supported)
    :param fused: ``None`` (default) runs torch's fused Adam kernel on devices that have it and a per-parameter
        update elsewhere; ``True`` requires the kernel; ``False`` always runs the per-parameter update
    :param decoupled_weight_decay: AdamW: shrink the parameters by ``lr * weight_decay`` instead of adding the
        penalty to the gradient
    """

    def __init__(
        self,
        params: Iterable[Any],
        lr: float = 1e-3,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        weight_decay: float = 0.0,
        amsgrad: bool = False,
        *,
        foreach: bool | None = None,
        maximize: bool = False,
        capturable: bool = False,
        differentiable: bool = False,
        fused: bool | None = None,
        decoupled_weight_decay: bool = False,
    ):
        if lr < 0.0:
            raise ValueError(f"Invalid learning rate: {lr}, expected lr >= 0")
        if not all(0.0 <= beta < 1.0 for beta in betas):
            raise ValueError(f"Invalid betas: {betas}, expected each in [0, 1)")
        if eps < 0.0:
            raise ValueError(f"Invalid eps: {eps}, expected eps >= 0")
        if weight_decay < 0.0:
            raise ValueError(f"Invalid weight_decay: {weight_decay}, expected weight_decay >= 0")
        if fused and foreach:
            raise ValueError("fused and foreach cannot both be True (as torch.optim.Adam): pass one of them")
        for name, value in (("capturable", capturable), ("differentiable", differentiable)):
            if value:
                raise ValueError(
                    f"EnsembleAdam supports {name}=False only, got {name}={value!r}; pass "
                    "policy_kwargs=dict(optimizer_class=torch.optim.Adam) for it (which also moves the heads a step "
                    "does not train)"
                )
        defaults = dict(
            lr=lr,
            betas=tuple(betas),
            eps=eps,
            weight_decay=weight_decay,
            amsgrad=bool(amsgrad),
            foreach=foreach,
            maximize=bool(maximize),
            fused=fused,
            decoupled_weight_decay=bool(decoupled_weight_decay),
            heads=False,
        )
        super().__init__(params, defaults)

    def __setstate__(self, state: dict[str, Any]) -> None:
        super().__setstate__(state)
        for group in self.param_groups:
            for key, value in ADAM_OPTION_DEFAULTS.items():
                group.setdefault(key, value)

    @th.no_grad()
    def step(self, closure: Any = None, head: int | th.Tensor | None = None) -> Any:  # type: ignore[override]
        """
        Perform one optimisation step.

        :param closure: re-evaluates the loss (as in ``torch.optim``)
        :param head: for head-batched groups, which heads to update: one index, a bool tensor of shape (K,),
            or ``None`` for every head. Heads left out keep their values and their Adam state.
        :return: the closure's loss, if any
        """
        loss = None
        if closure is not None:
            with th.enable_grad():
                loss = closure()
        for group in self.param_groups:
            # Ellipsis selects everything, also the 0-dim step counter of a body parameter
            rows: Any = head if (group["heads"] and isinstance(head, int)) else ...
            row_mask = head if (group["heads"] and isinstance(head, th.Tensor)) else None
            params = [param for param in group["params"] if param.grad is not None]
            if row_mask is None:
                self._adam_update_rows(group, params, rows)
            else:
                for param in params:
                    self._adam_update(group, param, rows, row_mask)
        return loss

    def _state(self, group: dict[str, Any], param: th.Tensor) -> dict[str, Any]:
        state = self.state[param]
        if len(state) == 0:
            state["exp_avg"] = th.zeros_like(param, memory_format=th.preserve_format)
            state["exp_avg_sq"] = th.zeros_like(param, memory_format=th.preserve_format)
            # one step count per head; float so that load_state_dict casts it with the other state tensors
            state["n_steps"] = th.zeros((param.shape[0],) if group["heads"] else (), dtype=param.dtype, device=param.device)
        if group["amsgrad"] and "max_exp_avg_sq" not in state:
            state["max_exp_avg_sq"] = th.zeros_like(param, memory_format=th.preserve_format)
        return state

    def _adam_update_rows(self, group: dict[str, Any], params: list[th.Tensor], rows: Any) -> None:
        """
        The update of every parameter of ``group`` at once, on the rows ``rows`` (one head, or ``...`` for all), by
        torch's fused Adam kernel (the one ``torch.optim.Adam(fused=True)`` runs: one pass over all the tensors,
        where a ``torch.optim.Adam`` without it takes a dozen kernels per parameter): a head-batched parameter goes to
        it one head's row at a time, each row with its head's step count. The arithmetic of :meth:`_adam_update`
        without a row mask, which updates the parameters one by one on devices without the kernel.
        """
        if not params:
            return
        has_kernel = params[0].device.type in FUSED_DEVICES
        if group["fused"] and not has_kernel:
            raise RuntimeError(f"fused=True: torch has no fused Adam kernel on {params[0].device}; pass fused=None or False")
        if group["fused"] is False or not has_kernel:
            for param in params:
                self._adam_update(group, param, rows, None)
            return

        # the kernel's tensors: a body parameter whole; a head-batched one as its K rows (views (in, out), each with
        # its head's step count ()), or the one row trained
        def split(tensor: th.Tensor) -> Any:
            if not group["heads"]:
                return [tensor]
            return tensor.unbind(0) if rows is ... else [tensor[rows]]

        keys = ("exp_avg", "exp_avg_sq", "n_steps") + (("max_exp_avg_sq",) if group["amsgrad"] else ())
        # values, grads, exp_avgs, exp_avg_sqs, n_steps[, max_exp_avg_sqs]
        lists: list[list[th.Tensor]] = [[] for _ in range(2 + len(keys))]
        for param in params:
            state = self._state(group, param)
            for pieces, tensor in zip(lists, (param, param.grad, *(state[key] for key in keys))):
                pieces.extend(split(tensor))
        values, grads, exp_avgs, exp_avg_sqs, n_steps, *max_exp_avg_sqs = lists
        th._foreach_add_(n_steps, 1)
        beta1, beta2 = group["betas"]
        adam = th._fused_adamw_ if group["decoupled_weight_decay"] else th._fused_adam_
        adam(
            values,
            grads,
            exp_avgs,
            exp_avg_sqs,
            max_exp_avg_sqs[0] if max_exp_avg_sqs else [],
            n_steps,
            lr=group["lr"],
            beta1=beta1,
            beta2=beta2,
            weight_decay=group["weight_decay"],
            eps=group["eps"],
            amsgrad=group["amsgrad"],
            maximize=group["maximize"],
        )

    def _adam_update(self, group: dict[str, Any], param: th.Tensor, rows: Any, row_mask: th.Tensor | None) -> None:
        beta1, beta2 = group["betas"]
        lr, weight_decay = group["lr"], group["weight_decay"]
        state = self._state(group, param)
        value, grad = param[rows], param.grad[rows]  # type: ignore[index]
        exp_avg, exp_avg_sq, n_steps = state["exp_avg"][rows], state["exp_avg_sq"][rows], state["n_steps"][rows]
        if group["maximize"]:
            grad = -grad
        # (K, 1, ..., 1): broadcasts a per-head quantity over each head's parameter dims
        per_head_shape = n_steps.shape + (1,) * (value.dim() - n_steps.dim())
        # 1 for the rows to update, 0 for the rows to leave as they are
        update: Any = 1.0
        if row_mask is not None:
            n_steps += row_mask.to(value.dtype)
            update = row_mask.to(value.dtype).reshape(per_head_shape)
        else:
            n_steps += 1
        if weight_decay != 0 and group["decoupled_weight_decay"]:
            value.mul_(1 - lr * weight_decay * update)
        elif weight_decay != 0:
            grad = grad.add(value, alpha=weight_decay)
        exp_avg.lerp_(grad, (1 - beta1) * update)
        exp_avg_sq.mul_(1 - (1 - beta2) * update).addcmul_(grad * update, grad, value=1 - beta2)
        second_moment = exp_avg_sq
        if group["amsgrad"]:
            # rows left out: their exp_avg_sq is unchanged and never above their running maximum
            second_moment = th.maximum(state["max_exp_avg_sq"][rows], exp_avg_sq, out=state["max_exp_avg_sq"][rows])
        steps = n_steps.clamp(min=1).reshape(per_head_shape)
        bias_correction1 = 1 - beta1**steps
        bias_correction2_sqrt = (1 - beta2**steps).sqrt()
        denom = (second_moment.sqrt() / bias_correction2_sqrt).add_(group["eps"])
        value.addcdiv_(exp_avg * update, denom * bias_correction1, value=-lr)


def ensemble_param_groups(body: list[th.Tensor], heads: list[th.Tensor]) -> list[dict[str, Any]]:
    """Parameter groups for :class:`EnsembleAdam`: the shared body, then the head-batched parameters."""
    return [{"params": body, "heads": False}, {"params": heads, "heads": True}]
