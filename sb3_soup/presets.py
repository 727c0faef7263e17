"""
The paper's model family (Figure 1, Table 1) as settings of one class, and the paper's hyper-parameters.

| preset       | actor heads | critic heads | confidence | masks       |
|--------------|-------------|--------------|------------|-------------|
| ddpg         | 1           | 1            | none       | off (p = 1) |
| ma_bddpg     | 1           | K            | none       | mask_prob   |
| multi_ddpg   | K           | 1            | none       | mask_prob   |
| dbddpg       | K           | K            | none       | mask_prob   |
| soup         | K           | K            | adaptive   | mask_prob   |
"""

from importlib import resources
from pathlib import Path
from typing import Any

from gymnasium import spaces

from sb3_soup.validation import check_head_counts, integer, number

# Values are either numbers or "K" (replaced by n_heads)
PRESETS: dict[str, dict[str, Any]] = {
    "ddpg": dict(n_actor_heads=1, n_critic_heads=1, confidence="none", mask_prob=1.0),
    "ma_bddpg": dict(n_actor_heads=1, n_critic_heads="K", confidence="none"),
    "multi_ddpg": dict(n_actor_heads="K", n_critic_heads=1, confidence="none"),
    "dbddpg": dict(n_actor_heads="K", n_critic_heads="K", confidence="none"),
    "soup": dict(n_actor_heads="K", n_critic_heads="K", confidence="adaptive"),
}

# SOUP's ensemble without a preset: K actor and K critic heads, and these
DEFAULT_CONFIDENCE = "adaptive"
DEFAULT_MASK_PROB = 0.5


PAPER_UPDATE: dict[str, Any] = dict(train_heads="active", target_q="own", policy_delay=1, target_policy_noise=0.0)
"""The paper's update (Algorithm 1): the episode's head pair, each critic head on its own target, no delayed or smoothed
updates; SOUP's training-scheme arguments as :func:`paper_settings` sets them (the defaults differ since 0.2.0)."""

PAPER_NOISE: dict[str, Any] = dict(noise_type="decaying_normal", noise_std=0.2, noise_decay=0.999995, noise_std_min=0.05)
"""The paper mode's exploration noise in the RL Zoo's keys (``hyperparams/soup_paper.yml``'s): Gaussian, of std 0.2 in
the [-1, 1] action scale decayed by 0.999995 per step down to 0.05 (a :class:`sb3_soup.DecayingNormalActionNoise`)."""


def paper_hyperparams() -> dict[str, Any]:
    """
    :return: :func:`paper_settings` with the exploration noise as the RL Zoo's keys (:data:`PAPER_NOISE`), as
        ``hyperparams/soup_paper.yml`` writes them (the experiment runner and the Zoo build the noise from them)
    """
    return dict(
        learning_rate=1e-4,
        critic_learning_rate=3e-4,
        buffer_size=1_000_000,
        learning_starts=1000,
        batch_size=1024,
        tau=1e-3,
        gamma=0.99,
        **PAPER_UPDATE,
        **PAPER_NOISE,
        policy_kwargs=dict(net_arch=dict(pi_body=[256], pi_head=[128], qf_body=[256, 256], qf_head=[128], qf_action_layer=1)),
    )


def paper_settings(action_space: spaces.Space) -> dict[str, Any]:
    """
    The paper's hyper-parameters and update (Section 5 and Algorithm 1), for ``SOUP(policy, env,
    **paper_settings(env.action_space))``: Adam with actor lr 1e-4 and critic lr 3e-4, gamma 0.99, tau 1e-3, batch 1024,
    a replay memory of 1e6, the paper's networks (actor (256, **128**), critic (256, 256, **128**) with the action
    joining at its second layer, LeakyReLU), one randomly drawn head pair trained per episode on its own target, no
    delayed or smoothed updates, the adaptive confidence's selection read as ``softmax(v / temperature)`` (eq. 8). Not
    in the paper, our choices: Gaussian exploration noise of std 0.2 in the [-1, 1] action scale decayed by 0.999995 per
    step down to 0.05 (``action_noise``, a :class:`sb3_soup.DecayingNormalActionNoise`, which needs the action space's
    shape), 1000 random steps first, and the confidence network's lr 1e-4 (with the selection's
    ``temperature_mode="absolute"``, :class:`AdaptiveConfidence`'s defaults, so that these settings go with any preset
    and strategy). K is the user's (the paper: 5 or 10), as are the preset and the mask probability (not in the paper;
    the model's default, :data:`DEFAULT_MASK_PROB`).

    :param action_space: the environment's action space (``env.action_space``)
    :return: SOUP constructor arguments
    """
    from sb3_soup.noise import zoo_action_noise

    if action_space.shape is None:
        raise ValueError(f"action_space must be the environment's Box action space, got {action_space!r}")
    return zoo_action_noise(paper_hyperparams(), action_space.shape)


def hyperparams_file(name: str = "soup") -> Path:
    """
    :param name: ``"soup"`` (the defaults' RL-Zoo entries) or ``"soup_paper"`` (the paper's settings)
    :return: the installed YAML file (the repository's ``hyperparams/`` folder, installed as ``sb3_soup.hyperparams``)
    """
    if name not in ("soup", "soup_paper"):
        raise ValueError(f"name must be 'soup' or 'soup_paper', got {name!r}")
    return Path(str(resources.files("sb3_soup.hyperparams") / f"{name}.yml"))


def normalize_preset_name(name: str) -> str:
    """Accept "MA-BDDPG", "multi-ddpg", "DBDDPG"... and return the key of :data:`PRESETS`."""
    if not isinstance(name, str):
        raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {name!r}")
    key = name.strip().lower().replace("-", "_")
    if key not in PRESETS:
        raise ValueError(f"preset must be one of {sorted(PRESETS)} (case and '-' or '_' do not matter), got {name!r}")
    return key


def resolve_preset(name: str, n_heads: int) -> dict[str, Any]:
    """Settings of a preset for ``n_heads`` heads."""
    return {key: (n_heads if value == "K" else value) for key, value in PRESETS[normalize_preset_name(name)].items()}


def resolve_model(
    n_heads: int,
    n_actor_heads: int | None,
    n_critic_heads: int | None,
    preset: str | None,
    confidence: Any,
    mask_prob: float | None,
) -> dict[str, Any]:
    """
    The model of the family that SOUP's arguments describe: head counts, confidence and mask probability from the
    explicit arguments, else the preset's, else the defaults (K x K heads, :data:`DEFAULT_CONFIDENCE`,
    :data:`DEFAULT_MASK_PROB`). A preset's head counts and confidence cannot be contradicted (its mask probability can).

    :return: ``n_heads``, ``n_actor_heads``, ``n_critic_heads``, ``confidence``, ``mask_prob`` and ``preset`` (its key)
    """
    n_heads = integer(1, "number of bootstrapped heads K")("n_heads", n_heads)
    given = dict(n_actor_heads=n_actor_heads, n_critic_heads=n_critic_heads, confidence=confidence, mask_prob=mask_prob)
    if isinstance(confidence, str):
        given["confidence"] = confidence.lower()  # checked by the policy, which builds the strategy
    if mask_prob is not None:
        meaning = "probability that a head sees a transition; 1 turns bootstrap off"
        given["mask_prob"] = number(0.0, 1.0, True, False, meaning)("mask_prob", mask_prob)
    settings: dict[str, Any] = dict(
        n_actor_heads=n_heads, n_critic_heads=n_heads, confidence=DEFAULT_CONFIDENCE, mask_prob=DEFAULT_MASK_PROB
    )
    if preset is not None:
        preset = normalize_preset_name(preset)
        for key, value in resolve_preset(preset, n_heads).items():
            if given.get(key) is not None and key != "mask_prob" and given[key] != value:
                raise ValueError(f"preset={preset!r} sets {key}={value!r}, but {key}={given[key]!r} was given: drop one")
            settings[key] = value
    settings.update({key: value for key, value in given.items() if value is not None})
    settings["n_actor_heads"], settings["n_critic_heads"] = check_head_counts(
        settings["n_actor_heads"], settings["n_critic_heads"]
    )
    return dict(settings, preset=preset, n_heads=n_heads)
