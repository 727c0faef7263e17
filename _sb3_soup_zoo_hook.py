"""
sb3-soup's import hook for the RL Zoo, imported at start-up by ``sb3_soup_zoo.pth`` (standard library only).

rl_zoo3 has no plugin mechanism and its scripts build ``--algo``'s choices from ``ALGOS`` as soon as they start.
This module puts a finder at the front of ``sys.meta_path`` that only answers for the rl_zoo3 modules SOUP registers
into (``sb3_soup.zoo.HOOKED_MODULES``): it lets the normal finders find them, and runs
``sb3_soup.zoo.on_import(module)`` right after each one executes. Nothing else is imported here (not torch, not
rl_zoo3, not sb3_soup) until rl_zoo3 itself is imported; any failure of the registration becomes a warning.

Disable it with ``SB3_SOUP_ZOO_HOOK=0`` (then use ``python -m sb3_soup.train``).
"""

import os
import sys

ENV_VAR = "SB3_SOUP_ZOO_HOOK"
# Must match sb3_soup.zoo.HOOKED_MODULES (a test checks it); spelled out so that start-up imports nothing else.
HOOKED_MODULES = frozenset(("rl_zoo3.utils", "rl_zoo3.hyperparams_opt", "rl_zoo3.exp_manager"))


def enabled() -> bool:
    """Whether the environment allows the hook (anything but 0, false, no, off)."""
    return os.environ.get(ENV_VAR, "1").strip().lower() not in ("0", "false", "no", "off")


def _register(module):
    try:
        from sb3_soup import zoo

        zoo.on_import(module)
    except Exception as exc:  # the Zoo must keep working without SOUP
        import warnings

        warnings.warn(
            f"sb3-soup could not register SOUP with the RL Zoo on import of {module.__name__} ({exc!r}); "
            f"--algo soup may be unavailable (python -m sb3_soup.train registers explicitly; {ENV_VAR}=0 disables "
            "this hook)",
            RuntimeWarning,
            stacklevel=2,
        )


class ZooFinder:
    """Meta path finder that wraps ``exec_module`` of the loaders of ``HOOKED_MODULES``; finds nothing itself."""

    @classmethod
    def find_spec(cls, fullname, path=None, target=None):
        if fullname not in HOOKED_MODULES:
            return None
        for finder in sys.meta_path:
            if finder is cls or getattr(finder, "find_spec", None) is None:
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                break
        else:
            return None
        loader = spec.loader
        exec_module = getattr(loader, "exec_module", None)
        if exec_module is None:
            return spec

        def exec_and_register(module):
            exec_module(module)
            _register(module)

        try:
            loader.exec_module = exec_and_register
        except AttributeError:  # a loader with __slots__: leave it alone
            pass
        return spec


def install():
    """Put the finder first on ``sys.meta_path`` (once), unless disabled by the environment."""
    if enabled() and not any(finder is ZooFinder for finder in sys.meta_path):
        sys.meta_path.insert(0, ZooFinder)


install()
