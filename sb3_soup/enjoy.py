"""
``python -m sb3_soup.enjoy ARGS``: the RL Zoo's ``enjoy`` (same arguments) with SOUP registered first, e.g.

    python -m sb3_soup.enjoy --algo soup --env Pendulum-v1 -f logs/

With the import hook (the default), ``python -m rl_zoo3.enjoy --algo soup`` does the same.
"""

from sb3_soup.zoo import register


def main() -> None:
    """Register SOUP with the Zoo, then run the Zoo's ``enjoy`` on ``sys.argv``."""
    register()
    from rl_zoo3.enjoy import enjoy

    enjoy()


if __name__ == "__main__":
    main()
