"""
The paper's model family (Figure 1, Table 1) as settings of one class.

| preset       | actor heads | critic heads | confidence | masks       |
|--------------|-------------|--------------|------------|-------------|
| ddpg         | 1           | 1            | none       | off (p = 1) |
| ma_bddpg     | 1           | K            | none       | mask_prob   |
| multi_ddpg   | K           | 1            | none       | mask_prob   |
| dbddpg       | K           | K            | none       | mask_prob   |
| soup         | K           | K            | adaptive   | mask_prob   |
"""

from typing import Any

# Values are either numbers or "K" (replaced by n_heads)
PRESETS: dict[str, dict[str, Any]] = {
    "ddpg": dict(n_actor_heads=1, n_critic_heads=1, confidence="none", mask_prob=1.0),
    "ma_bddpg": dict(n_actor_heads=1, n_critic_heads="K", confidence="none"),
    "multi_ddpg": dict(n_actor_heads="K", n_critic_heads=1, confidence="none"),
    "dbddpg": dict(n_actor_heads="K", n_critic_heads="K", confidence="none"),
    "soup": dict(n_actor_heads="K", n_critic_heads="K", confidence="adaptive"),
}


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
