"""
The rules that every module of sb3-soup checks its own arguments with (SOUP its own in ``SOUP.__init__``, the policy
its own, each confidence strategy its own), so that every argument is refused alike: ``number(0, 1, True, True,
"meaning")("alpha", value)``. Nothing here knows another module's arguments.

Every check raises a ``ValueError`` that names the parameter, the accepted values and what was given (value and type),
e.g. ``alpha must be a float in (0, 1) (FixedConfidence's confidence of a head in its own candidate), got '0.5'
(str)``.
Python and NumPy numbers are accepted alike (``np.float32(0.5)``, ``np.int64(3)``), and an integer given as a float
(``2.0``, as YAML or a sampler may give it; TD3 takes ``policy_delay=2.0``) as that integer; ``bool`` is never taken for a
number.
"""

import math
import os
import sys
from collections.abc import Callable, Sequence
from types import FrameType
from typing import Any

import numpy as np

Rule = Callable[[str, Any], Any]
"""A rule: ``rule(name, value)`` returns the value (numbers as Python ``int``/``float``/``bool``) or raises."""


def given(value: Any) -> str:
    return f"got {value!r} ({type(value).__name__})"


def _meaning(meaning: str) -> str:
    return f" ({meaning})" if meaning else ""


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def is_integral(value: Any) -> bool:
    """An integer, or a float that holds one (``2.0``)."""
    if isinstance(value, (float, np.floating)):
        return math.isfinite(value) and float(value).is_integer()
    return is_int(value)


def outside_stacklevel() -> int:
    """
    The ``stacklevel`` for ``warnings.warn``, called by the function that calls this, that points at the first frame
    outside sb3-soup and Stable-Baselines3: the user's line (or the RL Zoo's) however deep SB3 builds what warns.
    """
    import stable_baselines3

    import sb3_soup

    library_dirs = tuple(os.path.dirname(module.__file__ or "") + os.sep for module in (sb3_soup, stable_baselines3))
    frame: FrameType | None = sys._getframe(1)  # the function that warns: stacklevel 1
    level = 1
    while frame is not None and frame.f_code.co_filename.startswith(library_dirs):
        frame, level = frame.f_back, level + 1
    return level


def interval(low: float, high: float, low_open: bool, high_open: bool) -> str:
    """``(0, 1]``-style text of an interval."""

    def fmt(bound: float) -> str:
        return "inf" if math.isinf(bound) else f"{bound:g}"

    return f"{'(' if low_open else '['}{fmt(low)}, {fmt(high)}{')' if high_open else ']'}"


# ----- rule makers ------------------------------------------------------------------------------------------------


def integer(minimum: int, meaning: str = "") -> Rule:
    """An integer >= ``minimum``."""

    def rule(name: str, value: Any) -> int:
        if not is_integral(value) or value < minimum:
            raise ValueError(f"{name} must be an integer >= {minimum}{_meaning(meaning)}, {given(value)}")
        return int(value)

    return rule


def number(low: float, high: float, low_open: bool, high_open: bool, meaning: str = "") -> Rule:
    """A finite number in an interval."""

    def rule(name: str, value: Any) -> float:
        ok = is_number(value) and math.isfinite(value)
        if ok:
            ok = (value > low if low_open else value >= low) and (value < high if high_open else value <= high)
        if not ok:
            text = interval(low, high, low_open, high_open)
            raise ValueError(f"{name} must be a float in {text}{_meaning(meaning)}, {given(value)}")
        return float(value)

    return rule


def boolean(meaning: str = "") -> Rule:
    """``True`` or ``False`` (NumPy bools included)."""

    def rule(name: str, value: Any) -> bool:
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{name} must be True or False{_meaning(meaning)}, {given(value)}")
        return bool(value)

    return rule


def choice(choices: Sequence[str], meaning: str = "") -> Rule:
    """One of ``choices``."""

    def rule(name: str, value: Any) -> str:
        if not isinstance(value, str) or value not in choices:
            raise ValueError(f"{name} must be one of {tuple(choices)}{_meaning(meaning)}, {given(value)}")
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


def learning_rate(name: str, value: Any) -> Any:
    """A learning rate: a float > 0 or a schedule (a function of the progress remaining, from 1 to 0)."""
    if callable(value) or (is_number(value) and math.isfinite(value) and value > 0):
        return value
    raise ValueError(
        f"{name} must be a float > 0 or a schedule (a function of the progress remaining, from 1 to 0), {given(value)}"
    )


def seed(name: str, value: Any) -> int | None:
    """A seed: None or an integer in NumPy's seed range."""
    if value is None:
        return None
    if not is_int(value) or not 0 <= value < 2**32:
        raise ValueError(f"{name} must be None or an integer in [0, 2**32 - 1] (NumPy's seed range), {given(value)}")
    return int(value)


def any_integer(meaning: str = "") -> Rule:
    """An integer, of any sign."""

    def rule(name: str, value: Any) -> int:
        if not is_integral(value):
            raise ValueError(f"{name} must be an integer{_meaning(meaning)}, {given(value)}")
        return int(value)

    return rule


def keyword_dict(reserved: set[str], where: str, advice: str) -> Rule:
    """``None`` or a dict of keyword arguments that sets none of ``reserved`` (``advice`` says where they go)."""

    def rule(name: str, value: Any) -> Any:
        if value is None:
            return None
        if not isinstance(value, dict):
            raise ValueError(f"{name} must be None or a dict of {where} arguments, {given(value)}")
        taken = sorted(reserved & set(value))
        if taken:
            raise ValueError(f"{name} must not set {taken}: {advice}")
        return value

    return rule


def check_head_counts(n_actor_heads: Any, n_critic_heads: Any) -> tuple[int, int]:
    """
    Actor head k is paired with critic head k: as many actor as critic heads, or one of them alone (serving every pair).
    SOUP's arguments and its policy's (which can be built alone) are both checked by this rule.

    :param n_actor_heads: the actor's heads
    :param n_critic_heads: the critic's heads
    :return: both, as Python ints
    """
    n_actor_heads = integer(1, "number of actor heads")("n_actor_heads", n_actor_heads)
    n_critic_heads = integer(1, "number of critic heads")("n_critic_heads", n_critic_heads)
    if n_actor_heads != n_critic_heads and min(n_actor_heads, n_critic_heads) > 1:
        raise ValueError(
            "actor head k is paired with critic head k: n_actor_heads and n_critic_heads must be equal or one of them 1, "
            f"got n_actor_heads={n_actor_heads}, n_critic_heads={n_critic_heads}"
        )
    return n_actor_heads, n_critic_heads


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
