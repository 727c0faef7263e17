"""
Every argument rule of sb3-soup in one declarative table, :data:`RULES`: SOUP's constructor arguments, its policy's,
the bootstrapped buffers' and the confidence strategies'. Each rule is written once and used by whoever takes the
argument (``check("alpha", value)``), so the same parameter is refused with the same message everywhere.

Every check raises a ``ValueError`` that names the parameter, the accepted values and what was given (value and type),
e.g. ``alpha must be a float in (0, 1) (fixed confidence of a head in its own candidate), got '0.5' (str)``.
Python and NumPy numbers are accepted alike (``np.float32(0.5)``, ``np.int64(3)``); ``bool`` is never taken for a number.
"""

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.noise import ActionNoise

Rule = Callable[[str, Any], Any]
"""A rule: ``rule(name, value)`` returns the value (numbers as Python ``int``/``float``/``bool``) or raises."""

TRAIN_HEADS = ("active", "all", "all_critics")
TARGET_Q = ("own", "min_pair")
CONFIDENCE_STRATEGIES = ("none", "fixed", "decayed", "adaptive", "ucb")


def _given(value: Any) -> str:
    return f"got {value!r} ({type(value).__name__})"


def _meaning(meaning: str) -> str:
    return f" ({meaning})" if meaning else ""


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def interval(low: float, high: float, low_open: bool, high_open: bool) -> str:
    """``(0, 1]``-style text of an interval."""

    def fmt(bound: float) -> str:
        return "inf" if math.isinf(bound) else f"{bound:g}"

    return f"{'(' if low_open else '['}{fmt(low)}, {fmt(high)}{')' if high_open else ']'}"


# ----- rule makers ------------------------------------------------------------------------------------------------


def integer(minimum: int, meaning: str = "") -> Rule:
    """An integer >= ``minimum``."""

    def rule(name: str, value: Any) -> int:
        if not _is_int(value) or value < minimum:
            raise ValueError(f"{name} must be an integer >= {minimum}{_meaning(meaning)}, {_given(value)}")
        return int(value)

    return rule


def number(low: float, high: float, low_open: bool, high_open: bool, meaning: str = "") -> Rule:
    """A finite number in an interval."""

    def rule(name: str, value: Any) -> float:
        ok = _is_number(value) and math.isfinite(value)
        if ok:
            ok = (value > low if low_open else value >= low) and (value < high if high_open else value <= high)
        if not ok:
            text = interval(low, high, low_open, high_open)
            raise ValueError(f"{name} must be a float in {text}{_meaning(meaning)}, {_given(value)}")
        return float(value)

    return rule


def boolean(meaning: str = "") -> Rule:
    """``True`` or ``False`` (NumPy bools included)."""

    def rule(name: str, value: Any) -> bool:
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{name} must be True or False{_meaning(meaning)}, {_given(value)}")
        return bool(value)

    return rule


def choice(choices: Sequence[str], meaning: str = "") -> Rule:
    """One of ``choices``."""

    def rule(name: str, value: Any) -> str:
        if not isinstance(value, str) or value not in choices:
            raise ValueError(f"{name} must be one of {tuple(choices)}{_meaning(meaning)}, {_given(value)}")
        return value

    return rule


def optional(inner: Rule, meaning: str) -> Rule:
    """``None`` (``meaning`` says what it stands for) or what ``inner`` accepts."""

    def rule(name: str, value: Any) -> Any:
        if value is None:
            return None
        try:
            return inner(name, value)
        except ValueError as error:
            raise ValueError(f"{error} (or None: {meaning})") from None

    return rule


def _learning_rate(name: str, value: Any) -> Any:
    if callable(value):
        return value
    if not (_is_number(value) and math.isfinite(value) and value > 0):
        raise ValueError(
            f"{name} must be a float > 0 or a schedule (a function of the progress remaining, from 1 to 0), {_given(value)}"
        )
    return value


def _train_freq(name: str, value: Any) -> Any:
    if isinstance(value, (tuple, list)) and len(value) == 2 and isinstance(value[1], str):
        integer(1, "how many steps or episodes between training rounds")(f"{name}[0]", value[0])
        choice(("step", "episode"), "unit of train_freq")(f"{name}[1]", value[1])
        return value
    if not _is_int(value) or value < 1:
        raise ValueError(
            f"{name} must be an integer >= 1 (train every n steps) or a tuple (n, 'step' | 'episode'), {_given(value)}"
        )
    return int(value)


def _seed(name: str, value: Any) -> int | None:
    if value is None:
        return None
    if not _is_int(value) or not 0 <= value < 2**32:
        raise ValueError(f"{name} must be None or an integer in [0, 2**32 - 1] (NumPy's seed range), {_given(value)}")
    return int(value)


def _action_noise(name: str, value: Any) -> Any:
    if value is not None and not isinstance(value, ActionNoise):
        raise ValueError(
            f"{name} must be None (the built-in Gaussian noise: noise_std, noise_decay, noise_std_min) or an "
            f"instance of stable_baselines3.common.noise.ActionNoise, {_given(value)}"
        )
    return value


def _keyword_dict(reserved: set[str], where: str, advice: str) -> Rule:
    def rule(name: str, value: Any) -> Any:
        if value is None:
            return None
        if not isinstance(value, dict):
            raise ValueError(f"{name} must be None or a dict of {where} arguments, {_given(value)}")
        taken = sorted(reserved & set(value))
        if taken:
            raise ValueError(f"{name} must not set {taken}: {advice}")
        return value

    return rule


def _confidence(name: str, value: Any) -> Any:
    from sb3_soup.confidence import ConfidenceStrategy

    accepted = f"one of {CONFIDENCE_STRATEGIES} or an instance of a sb3_soup.ConfidenceStrategy subclass"
    if value is None:
        return None
    if isinstance(value, str):
        if value.lower() not in CONFIDENCE_STRATEGIES:
            raise ValueError(f"{name} must be {accepted}, {_given(value)}")
        return value.lower()
    if not isinstance(value, ConfidenceStrategy):
        hint = (
            " (it has a weights method: subclass sb3_soup.ConfidenceStrategy, an nn.Module, so that its state is saved)"
            if callable(getattr(value, "weights", None))
            else ""
        )
        raise ValueError(f"{name} must be {accepted} implementing weights(obs, q_matrix) -> W, {_given(value)}{hint}")
    if "_parameters" not in vars(value):
        raise ValueError(
            f"{name}: {type(value).__name__}.__init__ must call super().__init__() "
            "(a ConfidenceStrategy is an nn.Module, whose state is saved with the policy)"
        )
    return value


# ----- the table --------------------------------------------------------------------------------------------------

RULES: dict[str, Rule] = {
    # SOUP (SB3's off-policy arguments)
    "learning_rate": _learning_rate,
    "critic_learning_rate": optional(_learning_rate, "the same as learning_rate"),
    "buffer_size": integer(1, "replay buffer size"),
    "learning_starts": integer(0, "steps of random actions before learning"),
    "batch_size": integer(1, "minibatch size"),
    "tau": number(0.0, 1.0, True, False, "soft update coefficient"),
    "gamma": number(0.0, 1.0, False, False, "discount factor"),
    "train_freq": _train_freq,
    "gradient_steps": integer(-1, "gradient steps after each rollout, -1: as many as env steps"),
    "action_noise": _action_noise,
    "replay_buffer_kwargs": _keyword_dict(
        {"n_masks", "mask_prob"}, "replay buffer", "SOUP sets n_masks to its number of head pairs; pass mask_prob to SOUP"
    ),
    "optimize_memory_usage": boolean("memory efficient replay buffer"),
    "n_steps": integer(1, "steps of the n-step returns, 1: one-step TD targets"),
    "policy_kwargs": _keyword_dict(
        {"n_actor_heads", "n_critic_heads", "confidence", "confidence_kwargs"},
        "policy",
        "set them as SOUP arguments (n_heads, preset, confidence...)",
    ),
    "stats_window_size": integer(1, "episodes averaged in the rollout logs"),
    "seed": _seed,
    # SOUP: the ensemble and its training scheme
    "n_heads": integer(1, "number of bootstrapped heads K"),
    "n_actor_heads": optional(integer(1, "number of actor heads"), "n_heads"),
    "n_critic_heads": optional(integer(1, "number of critic heads"), "n_heads"),
    "mask_prob": number(0.0, 1.0, True, False, "probability that a head sees a transition; 1 turns bootstrap off"),
    "n_masks": integer(1, "the number of bootstrapped head pairs"),
    "n_critics": integer(1, "SB3's number of critics; SOUP's critics are its n_critic_heads"),
    "train_heads": choice(TRAIN_HEADS, "which head pairs each gradient step trains"),
    "target_q": choice(TARGET_Q, "which target critic heads each head bootstraps from"),
    "policy_delay": integer(1, "critic updates per actor and target update"),
    "target_policy_noise": number(0.0, math.inf, False, True, "std of the target action's smoothing noise, 0: none"),
    "target_noise_clip": number(0.0, math.inf, False, True, "limit of the target action's smoothing noise"),
    "noise_std": number(0.0, math.inf, False, True, "initial exploration noise std"),
    "noise_decay": number(0.0, 1.0, True, False, "noise std decay per env step"),
    "noise_std_min": number(0.0, math.inf, False, True, "lowest exploration noise std"),
    "check_finite": boolean("raise at the first NaN/inf observation, reward, Q value or loss"),
    # confidence strategies (SOUP passes them on)
    "confidence": _confidence,
    "alpha": number(0.0, 1.0, True, True, "fixed confidence of a head in its own candidate"),
    "decay": number(0.0, 1.0, True, False, "per-step decay of the decayed confidence"),
    "temperature": number(0.0, math.inf, True, True, "softmax temperature of the selection"),
    "temperature_mode": choice(("absolute", "relative"), "the temperature divides the E-Q values, or their spread"),
    "confidence_lr": number(0.0, math.inf, True, True, "confidence network learning rate"),
    "confidence_baseline": boolean("running-mean reward baseline in REINFORCE"),
    "ucb_lambda": number(0.0, math.inf, False, True, "weight of the UCB bonus"),
    "baseline_rate": number(0.0, 1.0, True, False, "update rate of the reward baseline"),
    "eps": number(0.0, 1.0, True, True, "lower clamp of the confidence"),
}


def check(name: str, value: Any) -> Any:
    """
    :param name: an argument of :data:`RULES`
    :param value: what the user passed
    :return: the value, numbers converted to Python ``int``/``float``/``bool``
    """
    return RULES[name](name, value)


def check_arguments(**kwargs: Any) -> dict[str, Any]:
    """
    :param kwargs: arguments (those without a rule pass through unchecked)
    :return: the arguments, each checked by its rule
    """
    return {name: (RULES[name](name, value) if name in RULES else value) for name, value in kwargs.items()}


def check_head_counts(n_actor_heads: int, n_critic_heads: int) -> None:
    """
    Actor head k is paired with critic head k: as many actor as critic heads, or one of them alone (serving every pair).

    :param n_actor_heads: the actor's heads
    :param n_critic_heads: the critic's heads
    """
    if n_actor_heads != n_critic_heads and min(n_actor_heads, n_critic_heads) > 1:
        raise ValueError(
            "actor head k is paired with critic head k: n_actor_heads and n_critic_heads must be equal or one of them 1, "
            f"got n_actor_heads={n_actor_heads}, n_critic_heads={n_critic_heads}"
        )


def all_finite(value: np.ndarray | dict[str, np.ndarray]) -> bool:
    """:return: whether every float of an array (or of a dict of arrays) is finite"""
    if isinstance(value, dict):
        return all(all_finite(item) for item in value.values())
    array = np.asarray(value)
    return not np.issubdtype(array.dtype, np.floating) or bool(np.isfinite(array).all())


def check_finite_env_output(kind: str, value: Any, when: str) -> None:
    """
    :param kind: what the environment returned ("observation", "reward")
    :param value: its value
    :param when: e.g. "by env.reset()" or "by the environment at step 42"
    :raises ValueError: when it holds a NaN or an inf
    """
    if not all_finite(value):
        raise ValueError(
            f"non-finite {kind} (NaN or inf) returned {when}: {value!r}. "
            "Fix the environment, wrap it in VecCheckNan to locate the cause, or pass check_finite=False"
        )
