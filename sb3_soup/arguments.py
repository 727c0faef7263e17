"""
SOUP's rules for the arguments it owns, checked once by ``SOUP.__init__`` (and by ``SOUP.load`` for the settings it
changes). The head counts, ``preset``, ``confidence`` and ``mask_prob`` are resolved by
:func:`sb3_soup.presets.resolve_model`; ``confidence_kwargs`` by the strategy, which takes them; SB3's arguments by SB3.
"""

import math
from typing import Any

from sb3_soup.noise import check_action_noise
from sb3_soup.policies import SET_BY_SOUP
from sb3_soup.validation import (
    Rule,
    any_integer,
    boolean,
    choice,
    integer,
    keyword_dict,
    learning_rate,
    number,
    optional,
    seed,
)

TRAIN_HEADS = ("active", "all", "all_critics")
TARGET_Q = ("own", "min_pair", "redq")

ARGUMENT_RULES: dict[str, Rule] = {
    "critic_learning_rate": optional(learning_rate, "the same as learning_rate"),
    "train_heads": choice(TRAIN_HEADS, "which head pairs each gradient step trains"),
    "target_q": choice(TARGET_Q, "which target critic heads each head bootstraps from"),
    "policy_delay": integer(1, "critic updates per actor and target update"),
    "target_policy_noise": number(0.0, math.inf, False, True, "std of the target action's smoothing noise, 0: none"),
    "target_noise_clip": number(0.0, math.inf, False, True, "limit of the target action's smoothing noise"),
    "check_finite": boolean("raise at the first NaN/inf observation, reward, Q value or loss"),
    "replay_buffer_kwargs": keyword_dict(
        {"n_masks", "mask_prob"}, "replay buffer", "SOUP sets n_masks to its number of head pairs; pass mask_prob to SOUP"
    ),
    "policy_kwargs": keyword_dict(
        set(SET_BY_SOUP), "policy", "set them as SOUP arguments (n_heads, preset, confidence, confidence_kwargs...)"
    ),
    # SB3's arguments are SB3's to check, but for those SB3 would fail on without naming them
    "buffer_size": any_integer("replay buffer size"),
    "n_steps": any_integer("steps of the n-step returns, 1 or less: one-step TD targets"),
    "seed": seed,
    "action_noise": check_action_noise,
}
"""SOUP's rule for each argument it checks (:func:`check_arguments`)."""


def check_arguments(**kwargs: Any) -> dict[str, Any]:
    """
    :param kwargs: SOUP's arguments (those without a rule in :data:`sb3_soup.arguments.ARGUMENT_RULES` pass through
        unchecked)
    :return: the arguments, each checked by its rule (numbers as Python ``int``/``float``/``bool``)
    """
    return {name: (ARGUMENT_RULES[name](name, value) if name in ARGUMENT_RULES else value) for name, value in kwargs.items()}
