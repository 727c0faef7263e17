"""
``python -m sb3_soup.train ARGS``: the RL Zoo's ``train`` (same arguments) with SOUP registered first, e.g.

    python -m sb3_soup.train --algo soup --env Pendulum-v1

It works with the import hook disabled (``SB3_SOUP_ZOO_HOOK=0``); with the hook,
``python -m rl_zoo3.train --algo soup`` does the same.
"""

from sb3_soup.zoo import register


def main() -> None:
    """Register SOUP with the Zoo, then run the Zoo's ``train`` on ``sys.argv``."""
    register()
    from rl_zoo3.train import train

    train()


if __name__ == "__main__":
    main()
