"""
SOUP in the RL Zoo (rl_zoo3), which has no plugin mechanism: register into its dictionaries.

``register()`` adds ``"soup"`` to ``rl_zoo3.utils.ALGOS``, the optuna sampler and converter to
``rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER``/``HYPERPARAMS_CONVERTER`` (``-optimize``), and makes
``ExperimentManager`` read ``hyperparams/soup.yml`` (installed as ``sb3_soup.hyperparams``) when ``--algo soup``
comes without ``--conf-file``, and build a :class:`sb3_soup.DecayingNormalActionNoise` for the entries whose
``noise_type`` is ``'decaying_normal'`` (with ``noise_std``, ``noise_decay``, ``noise_std_min``: the paper mode's noise,
``hyperparams/soup_paper.yml``).
Every step is idempotent. The import hook installed by ``sb3_soup_zoo.pth`` (``_sb3_soup_zoo_hook``) calls
``on_import`` on each of those rl_zoo3 modules right after it executes, so ``python -m rl_zoo3.train --algo soup``
works with no user action; ``python -m sb3_soup.train`` calls ``register()`` itself.
"""

import functools
import inspect
import warnings
from types import ModuleType
from typing import Any

from sb3_soup.presets import hyperparams_file

ALGO_NAME = "soup"
DEFAULT_CONF_FILE = hyperparams_file("soup")

_WRAPPED_MARK = "_sb3_soup_default_conf"
_NOISE_MARK = "_sb3_soup_decaying_noise"


def register_algo(utils: ModuleType) -> None:
    """
    Add SOUP to ``ALGOS`` (what ``--algo`` accepts and what the Zoo builds and loads).

    :param utils: the ``rl_zoo3.utils`` module
    """
    from sb3_soup.soup import SOUP

    current = utils.ALGOS.get(ALGO_NAME)
    if current is None:
        utils.ALGOS[ALGO_NAME] = SOUP
    elif current is not SOUP:
        warnings.warn(f"rl_zoo3 already has an algorithm {ALGO_NAME!r} ({current!r}); sb3-soup leaves it in place")


def register_optimizer(hyperparams_opt: ModuleType) -> None:
    """
    Add the optuna sampler (and the converter used by ``--trial-id``) of SOUP's hyper-parameters.

    :param hyperparams_opt: the ``rl_zoo3.hyperparams_opt`` module
    """
    from sb3_soup.zoo_hyperparams import convert_soup_params, sample_soup_params

    hyperparams_opt.HYPERPARAMS_SAMPLER.setdefault(ALGO_NAME, sample_soup_params)
    # rl_zoo3 < 2.4 has no converter table
    converters = getattr(hyperparams_opt, "HYPERPARAMS_CONVERTER", None)
    if converters is not None:
        converters.setdefault(ALGO_NAME, convert_soup_params)


def use_default_conf_file(exp_manager: ModuleType) -> None:
    """
    Make ``ExperimentManager`` read sb3-soup's ``soup.yml`` for ``--algo soup`` when no ``--conf-file`` is given
    (the Zoo looks for ``hyperparams/<algo>.yml`` inside its own package otherwise).

    :param exp_manager: the ``rl_zoo3.exp_manager`` module
    """
    manager_class = exp_manager.ExperimentManager
    original_init = manager_class.__init__
    if getattr(original_init, _WRAPPED_MARK, False):
        return
    signature = inspect.signature(original_init)

    @functools.wraps(original_init)
    def __init__(self: Any, *args: Any, **kwargs: Any) -> None:
        original_init(self, *args, **kwargs)
        config = signature.bind(self, *args, **kwargs).arguments.get("config")
        if self.algo == ALGO_NAME and not config:
            self.config = str(DEFAULT_CONF_FILE)

    setattr(__init__, _WRAPPED_MARK, True)
    manager_class.__init__ = __init__


def use_decaying_noise(exp_manager: ModuleType) -> None:
    """
    Make ``ExperimentManager`` build a :class:`sb3_soup.DecayingNormalActionNoise` for ``noise_type: 'decaying_normal'``
    (``noise_std``, ``noise_decay``, ``noise_std_min``; see :func:`sb3_soup.noise.zoo_action_noise`); the Zoo's own
    noise types are left to it.

    :param exp_manager: the ``rl_zoo3.exp_manager`` module
    """
    from sb3_soup.noise import DECAYING_NORMAL, is_decaying_normal, zoo_action_noise

    manager_class = exp_manager.ExperimentManager
    original = manager_class._preprocess_action_noise
    if getattr(original, _NOISE_MARK, False):
        return

    @functools.wraps(original)
    def _preprocess_action_noise(self: Any, hyperparams: dict[str, Any], saved_hyperparams: dict[str, Any], env: Any) -> Any:
        if is_decaying_normal(hyperparams):
            decay, floor = hyperparams.get("noise_decay", 1.0), hyperparams.get("noise_std_min", 0.0)
            print(f"Applying {DECAYING_NORMAL} noise with std {hyperparams['noise_std']}, decay {decay} and floor {floor}")
            hyperparams = zoo_action_noise(hyperparams, env.action_space.shape)
        return original(self, hyperparams, saved_hyperparams, env)

    setattr(_preprocess_action_noise, _NOISE_MARK, True)
    manager_class._preprocess_action_noise = _preprocess_action_noise


def register_experiment_manager(exp_manager: ModuleType) -> None:
    """
    :param exp_manager: the ``rl_zoo3.exp_manager`` module (see :func:`use_default_conf_file`, :func:`use_decaying_noise`)
    """
    use_default_conf_file(exp_manager)
    use_decaying_noise(exp_manager)


_REGISTRATIONS = {
    "rl_zoo3.utils": register_algo,
    "rl_zoo3.hyperparams_opt": register_optimizer,
    "rl_zoo3.exp_manager": register_experiment_manager,
}

#: the rl_zoo3 modules the import hook watches
HOOKED_MODULES = tuple(_REGISTRATIONS)


def on_import(module: ModuleType) -> None:
    """
    Register what belongs to one rl_zoo3 module, right after it was executed (called by the import hook).

    :param module: one of the modules in ``HOOKED_MODULES``
    """
    _REGISTRATIONS[module.__name__](module)


def register() -> None:
    """Register SOUP with the RL Zoo: ``--algo soup``, its default hyper-parameters and ``-optimize``. Idempotent."""
    import importlib

    for name, registration in _REGISTRATIONS.items():
        registration(importlib.import_module(name))
