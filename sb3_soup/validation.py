"""
Argument checks shared by SOUP, its policy, buffers and confidence strategies.

Every check raises a ``ValueError`` that names the parameter, the accepted values and what was given (value and type),
e.g. ``alpha must be a float in (0, 1) (fixed confidence of a head in its own candidate), got '0.5' (str)``.
Python and NumPy numbers are accepted alike (``np.float32(0.5)``, ``np.int64(3)``); ``bool`` is never taken for a number.
"""

import math
from collections.abc import Sequence
from typing import Any

import numpy as np


def _given(value: Any) -> str:
    return f"got {value!r} ({type(value).__name__})"


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def check_int(name: str, value: Any, minimum: int = 1, meaning: str = "") -> int:
    """
    :param name: the parameter's name, as the user passes it
    :param value: what the user passed
    :param minimum: smallest accepted value
    :param meaning: what the parameter is, for the message
    :return: ``value`` as a Python int
    """
    if not _is_int(value) or value < minimum:
        what = f" ({meaning})" if meaning else ""
        raise ValueError(f"{name} must be an integer >= {minimum}{what}, {_given(value)}")
    return int(value)


def interval(low: float, high: float, low_open: bool, high_open: bool) -> str:
    """``(0, 1]``-style text of an interval."""

    def fmt(bound: float) -> str:
        return "inf" if math.isinf(bound) else f"{bound:g}"

    return f"{'(' if low_open else '['}{fmt(low)}, {fmt(high)}{')' if high_open else ']'}"


def check_float(
    name: str,
    value: Any,
    low: float = -math.inf,
    high: float = math.inf,
    low_open: bool = False,
    high_open: bool = False,
    meaning: str = "",
) -> float:
    """
    A finite number in an interval.

    :param name: the parameter's name
    :param value: what the user passed
    :param low: lower bound
    :param high: upper bound
    :param low_open: whether ``low`` itself is excluded
    :param high_open: whether ``high`` itself is excluded
    :param meaning: what the parameter is, for the message
    :return: ``value`` as a Python float
    """
    ok = _is_number(value) and math.isfinite(value)
    if ok:
        ok = (value > low if low_open else value >= low) and (value < high if high_open else value <= high)
    if not ok:
        what = f" ({meaning})" if meaning else ""
        raise ValueError(f"{name} must be a float in {interval(low, high, low_open, high_open)}{what}, {_given(value)}")
    return float(value)


def check_bool(name: str, value: Any, meaning: str = "") -> bool:
    """
    :param name: the parameter's name
    :param value: what the user passed (``True``/``False``, NumPy bools included)
    :param meaning: what the parameter is, for the message
    :return: ``value`` as a Python bool
    """
    if not isinstance(value, (bool, np.bool_)):
        what = f" ({meaning})" if meaning else ""
        raise ValueError(f"{name} must be True or False{what}, {_given(value)}")
    return bool(value)


def check_choice(name: str, value: Any, choices: Sequence[str], meaning: str = "") -> str:
    """
    :param name: the parameter's name
    :param value: what the user passed
    :param choices: accepted strings
    :param meaning: what the parameter is, for the message
    :return: ``value``
    """
    if not isinstance(value, str) or value not in choices:
        what = f" ({meaning})" if meaning else ""
        raise ValueError(f"{name} must be one of {tuple(choices)}{what}, {_given(value)}")
    return value


def check_learning_rate(name: str, value: Any) -> None:
    """
    :param name: the parameter's name
    :param value: a float > 0 or a schedule (a callable of the progress remaining, from 1 to 0)
    """
    if callable(value):
        return
    if not (_is_number(value) and math.isfinite(value) and value > 0):
        raise ValueError(
            f"{name} must be a float > 0 or a schedule (a function of the progress remaining, from 1 to 0), {_given(value)}"
        )
