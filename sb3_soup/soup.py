"""SOUP: Self-Adaptive Double Bootstrapped DDPG, as a Stable-Baselines3 off-policy algorithm."""

import inspect
import io
import math
import pathlib
import warnings
from collections.abc import Callable, Iterable
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.save_util import load_from_pkl
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, PyTorchObs, Schedule
from stable_baselines3.common.utils import update_learning_rate

try:  # SB3 >= 2.6
    from stable_baselines3.common.utils import FloatSchedule as _as_schedule
except ImportError:  # pragma: no cover
    from stable_baselines3.common.utils import get_schedule_fn as _as_schedule  # type: ignore[assignment]

from sb3_soup.buffers import (
    BootstrappedDictReplayBuffer,
    BootstrappedDictReplayBufferSamples,
    BootstrappedReplayBuffer,
    BootstrappedReplayBufferSamples,
    check_mask_args,
)
from sb3_soup.confidence import ConfidenceRollout, ConfidenceStrategy, check_strategy, check_update_logs
from sb3_soup.losses import actor_loss, critic_loss, td_target
from sb3_soup.networks import EnsembleActor, EnsembleCritic, soft_update
from sb3_soup.optim import EnsembleAdam
from sb3_soup.persistence import capture_rng_state, restore_rng_state
from sb3_soup.policies import MlpPolicy, MultiInputPolicy, Selection, SOUPPolicy, TrainedHeads
from sb3_soup.presets import normalize_preset_name, resolve_preset
from sb3_soup.saving import SAVE_FORMAT_VERSION, check_saved_format, package_version, read_saved_data
from sb3_soup.validation import check_bool, check_choice, check_float, check_int, check_learning_rate

SelfSOUP = TypeVar("SelfSOUP", bound="SOUP")
__version__ = package_version()
Samples = BootstrappedReplayBufferSamples | BootstrappedDictReplayBufferSamples

TRAIN_HEADS = ("active", "all", "all_critics")
TARGET_Q = ("own", "min_pair")


def _all_finite(value: np.ndarray | dict[str, np.ndarray]) -> bool:
    if isinstance(value, dict):
        return all(_all_finite(item) for item in value.values())
    array = np.asarray(value)
    return not np.issubdtype(array.dtype, np.floating) or bool(np.isfinite(array).all())


def _check_train_freq(name: str, value: Any) -> Any:
    if isinstance(value, (tuple, list)) and len(value) == 2 and isinstance(value[1], str):
        check_int(f"{name}[0]", value[0], 1, "how many steps or episodes between training rounds")
        check_choice(f"{name}[1]", value[1], ("step", "episode"), "unit of train_freq")
        return value
    try:
        return check_int(name, value, 1)
    except ValueError:
        raise ValueError(
            f"{name} must be an integer >= 1 (train every n steps) or a tuple (n, 'step' | 'episode'), "
            f"got {value!r} ({type(value).__name__})"
        ) from None


def _check_seed(name: str, value: Any) -> int | None:
    if value is None:
        return None
    seed = check_int(name, value, 0, "or None")
    if seed >= 2**32:
        raise ValueError(f"{name} must be None or an integer in [0, 2**32 - 1] (NumPy's seed range), got {value!r}")
    return seed


def _check_action_noise(name: str, value: Any) -> Any:
    if value is not None and not isinstance(value, ActionNoise):
        raise ValueError(
            f"{name} must be None (the built-in decayed Gaussian noise: noise_std, noise_decay, noise_std_min) or an "
            f"instance of stable_baselines3.common.noise.ActionNoise, got {value!r} ({type(value).__name__})"
        )
    return value


def _check_replay_buffer_kwargs(name: str, value: Any) -> Any:
    if value is None:
        return value
    if not isinstance(value, dict):
        raise ValueError(f"{name} must be None or a dict of replay buffer arguments, got {value!r} ({type(value).__name__})")
    reserved = sorted({"n_masks", "mask_prob"} & set(value))
    if reserved:
        raise ValueError(
            f"{name} must not set {reserved}: SOUP sets n_masks to its number of head pairs; pass mask_prob to SOUP"
        )
    return value


def _check_policy_kwargs(name: str, value: Any) -> Any:
    if value is None:
        return value
    if not isinstance(value, dict):
        raise ValueError(f"{name} must be None or a dict of policy arguments, got {value!r} ({type(value).__name__})")
    reserved = sorted({"n_actor_heads", "n_critic_heads", "confidence", "confidence_kwargs"} & set(value))
    if reserved:
        raise ValueError(f"{name} must not set {reserved}: set them as SOUP arguments (n_heads, preset, confidence...)")
    return value


def _float_check(low: float, high: float, low_open: bool, high_open: bool, meaning: str) -> Callable[[str, Any], float]:
    return lambda name, value: check_float(name, value, low, high, low_open, high_open, meaning)


def _int_check(minimum: int, meaning: str) -> Callable[[str, Any], int]:
    return lambda name, value: check_int(name, value, minimum, meaning)


def _bool_check(meaning: str) -> Callable[[str, Any], bool]:
    return lambda name, value: check_bool(name, value, meaning)


def _lr_check(name: str, value: Any) -> Any:
    check_learning_rate(name, value)
    return value


# One check per constructor argument (by name): SOUP(...) and SOUP.load(..., **kwargs) use them
_ARGUMENT_CHECKS: dict[str, Callable[[str, Any], Any]] = {
    "learning_rate": _lr_check,
    "critic_learning_rate": _lr_check,
    "buffer_size": _int_check(1, "replay buffer size"),
    "learning_starts": _int_check(0, "steps of random actions before learning"),
    "batch_size": _int_check(1, "minibatch size"),
    "tau": _float_check(0.0, 1.0, True, False, "soft update coefficient"),
    "gamma": _float_check(0.0, 1.0, False, False, "discount factor"),
    "train_freq": _check_train_freq,
    "gradient_steps": _int_check(-1, "gradient steps after each rollout, -1: as many as env steps"),
    "action_noise": _check_action_noise,
    "replay_buffer_kwargs": _check_replay_buffer_kwargs,
    "optimize_memory_usage": _bool_check("memory efficient replay buffer"),
    "alpha": _float_check(0.0, 1.0, True, True, "fixed confidence of a head in its own candidate"),
    "decay": _float_check(0.0, 1.0, True, False, "per-step decay of the decayed confidence"),
    "temperature": _float_check(0.0, math.inf, True, True, "softmax temperature of the selection"),
    "confidence_lr": _float_check(0.0, math.inf, True, True, "confidence network learning rate"),
    "confidence_baseline": _bool_check("running-mean reward baseline in REINFORCE"),
    "ucb_lambda": _float_check(0.0, math.inf, False, True, "weight of the UCB bonus"),
    "mask_prob": _float_check(0.0, 1.0, True, False, "probability that a head sees a transition; 1 turns bootstrap off"),
    "train_heads": lambda name, value: check_choice(name, value, TRAIN_HEADS, "which head pairs each gradient step trains"),
    "target_q": lambda name, value: check_choice(name, value, TARGET_Q, "which target critic heads each head bootstraps from"),
    "policy_delay": _int_check(1, "critic updates per actor and target update"),
    "target_policy_noise": _float_check(0.0, math.inf, False, True, "std of the target action's smoothing noise, 0: none"),
    "target_noise_clip": _float_check(0.0, math.inf, False, True, "limit of the target action's smoothing noise"),
    "noise_std": _float_check(0.0, math.inf, False, True, "initial exploration noise std"),
    "noise_decay": _float_check(0.0, 1.0, True, False, "noise std decay per env step"),
    "noise_std_min": _float_check(0.0, math.inf, False, True, "lowest exploration noise std"),
    "check_finite": _bool_check("raise at the first NaN/inf observation, reward, Q value or loss"),
    "stats_window_size": _int_check(1, "episodes averaged in the rollout logs"),
    "policy_kwargs": _check_policy_kwargs,
    "seed": _check_seed,
}

# Fixed by a saved model: SOUP.load refuses to change them (the networks and the strategy are built from them)
_STRUCTURAL_ARGUMENTS = (
    "n_heads",
    "n_actor_heads",
    "n_critic_heads",
    "preset",
    "confidence",
    "alpha",
    "decay",
    "temperature",
    "confidence_lr",
    "confidence_baseline",
    "ucb_lambda",
    "policy",
)


class SOUP(OffPolicyAlgorithm):
    """
    Self-Adaptive Double Bootstrapped DDPG (SOUP).

    Paper: https://www.ijcai.org/proceedings/2018/0444.pdf (Zheng et al., IJCAI 2018).
    The details the paper leaves open are fixed as in the project's design spec (see README).
    DDPG with a bootstrapped actor and critic (shared bodies, K heads): every actor head proposes an action,
    every critic head scores every proposal, a confidence strategy weights the scores and the best-rated
    proposal is executed (eq. 7). Each episode trains one randomly drawn (actor head, critic head) pair on the
    transitions its bootstrap mask lets it see (Algorithm 1), or every pair at once (``train_heads="all"``).

    :param policy: The policy model to use (MlpPolicy, MultiInputPolicy)
    :param env: The environment to learn from (if registered in Gym, can be str)
    :param learning_rate: actor learning rate for Adam (the paper: 1e-4); it can be a function of the current
        progress remaining (from 1 to 0)
    :param critic_learning_rate: critic learning rate (the paper: 3e-4), float or schedule
    :param buffer_size: size of the replay buffer
    :param learning_starts: how many steps of the model to collect transitions for before learning starts
        (uniformly random actions until then)
    :param batch_size: Minibatch size for each gradient update (the paper: 1024)
    :param tau: the soft update coefficient ("Polyak update", between 0 and 1) (the paper: 1e-3)
    :param gamma: the discount factor
    :param train_freq: Update the model every ``train_freq`` steps. Alternatively pass a tuple of frequency and unit
        like ``(5, "step")`` or ``(2, "episode")``.
    :param gradient_steps: How many gradient steps to do after each rollout (-1: as many as env steps)
    :param action_noise: replaces the built-in decayed Gaussian exploration noise when given (SB3 ``ActionNoise``)
    :param replay_buffer_class: Replay buffer class: a :class:`BootstrappedReplayBuffer` (default) or
        :class:`BootstrappedDictReplayBuffer` subclass, since SOUP needs the masks
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer
        (needs ``replay_buffer_kwargs=dict(handle_timeout_termination=False)``, as in SB3)
    :param n_heads: number of bootstrapped heads K
    :param n_actor_heads: actor heads (default: ``n_heads``, or the preset's)
    :param n_critic_heads: critic heads (default: ``n_heads``, or the preset's)
    :param preset: one of the paper's models: "ddpg", "ma_bddpg", "multi_ddpg", "dbddpg", "soup"
        (sets head counts and confidence; see :data:`sb3_soup.PRESETS`)
    :param confidence: confidence strategy of the E-Critic layer: "none", "fixed", "decayed", "adaptive"
        (default, or the preset's), "ucb" (optimistic selection) or a :class:`sb3_soup.ConfidenceStrategy` instance
    :param alpha: fixed confidence of a critic head in its own candidate (``confidence="fixed"``), in (0, 1)
    :param decay: per-step decay of the confidence (``confidence="decayed"``), in (0, 1]
    :param temperature: softmax temperature of the selection policy trained by REINFORCE (``"adaptive"``), > 0
    :param confidence_lr: learning rate of the confidence network (``"adaptive"``)
    :param confidence_baseline: subtract a running-mean reward baseline in REINFORCE (False: the paper's raw reward)
    :param ucb_lambda: weight of the disagreement bonus of the optimistic selection (``confidence="ucb"``): while
        exploring, candidates are rated ``mean + ucb_lambda * std`` over the critic heads (SUNRISE)
    :param mask_prob: probability that a head sees a transition (Bernoulli masks), in (0, 1]; 1 turns bootstrap off
        (default 0.5, 1.0 for the "ddpg" preset)
    :param train_heads: "active": train the episode's active head pair (the paper); "all": every head pair
        on each minibatch, each with its own masked loss (Bootstrapped DQN style); "all_critics": every critic head, the
        active pair's actor head
    :param target_q: the value of the next state each critic head bootstraps from (eq. 4): "own", its own target head's
        (the paper); "min_pair", the smaller of its own target head's and one random other's (clipped double Q across
        the ensemble, as REDQ); with one critic head both are "own"
    :param policy_delay: the actor and the target networks are updated once every ``policy_delay`` critic updates
        (TD3's delayed policy updates; the paper: 1)
    :param target_policy_noise: std of the Gaussian noise added to the target actions (TD3's target policy smoothing;
        the paper: 0, none), in the [-1, 1] scaled action space
    :param target_noise_clip: limit of the absolute value of that noise
    :param noise_std: initial std of the Gaussian exploration noise (in the [-1, 1] scaled action space)
    :param noise_decay: multiplicative decay of the noise std per environment step, in (0, 1]
    :param noise_std_min: the noise std never goes below this
    :param check_finite: raise a clear error as soon as an observation, reward, loss or Q value is NaN or inf
    :param stats_window_size: Window size for the rollout logging, specifying the number of episodes to average
        the reported success rate, mean episode length, and mean reward over
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation (``net_arch``, ``activation_fn``...)
    :param verbose: Verbosity level: 0 for no output, 1 for info messages (such as device or wrappers used), 2 for
        debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run.
        Setting it to auto, the code will be run on the GPU if possible.
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: SOUPPolicy
    actor: EnsembleActor
    actor_target: EnsembleActor
    critic: EnsembleCritic
    critic_target: EnsembleCritic

    def __init__(
        self,
        policy: str | type[SOUPPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-4,
        critic_learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 1000,
        batch_size: int = 1024,
        tau: float = 1e-3,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_heads: int = 5,
        n_actor_heads: int | None = None,
        n_critic_heads: int | None = None,
        preset: str | None = None,
        confidence: str | ConfidenceStrategy | None = None,
        alpha: float = 0.5,
        decay: float = 0.9995,
        temperature: float = 1.0,
        confidence_lr: float = 1e-4,
        confidence_baseline: bool = True,
        ucb_lambda: float = 1.0,
        mask_prob: float | None = None,
        train_heads: str = "active",
        target_q: str = "own",
        policy_delay: int = 1,
        target_policy_noise: float = 0.0,
        target_noise_clip: float = 0.5,
        noise_std: float = 0.2,
        noise_decay: float = 0.999995,
        noise_std_min: float = 0.05,
        check_finite: bool = True,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        settings = self._resolve_settings(n_heads, n_actor_heads, n_critic_heads, preset, confidence, mask_prob)
        args = self._check_arguments(
            learning_rate=learning_rate,
            critic_learning_rate=critic_learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            action_noise=action_noise,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            alpha=alpha,
            decay=decay,
            temperature=temperature,
            confidence_lr=confidence_lr,
            confidence_baseline=confidence_baseline,
            ucb_lambda=ucb_lambda,
            train_heads=train_heads,
            target_q=target_q,
            policy_delay=policy_delay,
            target_policy_noise=target_policy_noise,
            target_noise_clip=target_noise_clip,
            noise_std=noise_std,
            noise_decay=noise_decay,
            noise_std_min=noise_std_min,
            check_finite=check_finite,
            stats_window_size=stats_window_size,
            policy_kwargs=policy_kwargs,
            seed=seed,
        )
        policy_kwargs = dict(policy_kwargs or {})

        super().__init__(
            policy,
            env,
            learning_rate,
            args["buffer_size"],
            args["learning_starts"],
            args["batch_size"],
            args["tau"],
            args["gamma"],
            train_freq,
            args["gradient_steps"],
            action_noise=action_noise,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=args["optimize_memory_usage"],
            policy_kwargs=policy_kwargs,
            stats_window_size=args["stats_window_size"],
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            sde_support=False,
            supported_action_spaces=(spaces.Box,),
            support_multi_env=True,
        )
        self.critic_learning_rate = critic_learning_rate
        self.n_heads: int = settings["n_heads"]
        self.preset_name: str | None = settings["preset"]
        self.n_actor_heads: int = settings["n_actor_heads"]
        self.n_critic_heads: int = settings["n_critic_heads"]
        self.confidence = settings["confidence"]
        self.mask_prob: float = settings["mask_prob"]
        self.alpha: float = args["alpha"]
        self.decay: float = args["decay"]
        self.temperature: float = args["temperature"]
        self.confidence_lr: float = args["confidence_lr"]
        self.confidence_baseline: bool = args["confidence_baseline"]
        self.ucb_lambda: float = args["ucb_lambda"]
        self.train_heads: str = args["train_heads"]
        self.target_q: str = args["target_q"]
        self.policy_delay: int = args["policy_delay"]
        self.target_policy_noise: float = args["target_policy_noise"]
        self.target_noise_clip: float = args["target_noise_clip"]
        self.noise_std: float = args["noise_std"]
        self.noise_decay: float = args["noise_decay"]
        self.noise_std_min: float = args["noise_std_min"]
        self.check_finite: bool = args["check_finite"]
        self.exploration_std = self.noise_std
        # Saved with the model: which sb3-soup wrote it, in which save format (see sb3_soup.saving)
        self._sb3_soup_format = SAVE_FORMAT_VERSION
        self._sb3_soup_version = __version__

        self.policy_kwargs.update(
            n_actor_heads=self.n_actor_heads,
            n_critic_heads=self.n_critic_heads,
            confidence=self.confidence,
            confidence_kwargs=dict(
                alpha=self.alpha,
                decay=self.decay,
                lr=self.confidence_lr,
                temperature=self.temperature,
                baseline=self.confidence_baseline,
                ucb_lambda=self.ucb_lambda,
            ),
        )
        # Per env: the head pair trained during its current episode (drawn at each episode start)
        self._active_heads: np.ndarray | None = None
        # Selections made while acting, kept for on-policy confidence strategies until the next update
        self._pending_selection: tuple[PyTorchObs, th.Tensor, th.Tensor] | None = None
        self._confidence_rollout: list[tuple[PyTorchObs, th.Tensor, th.Tensor, th.Tensor]] = []
        self._reset_ensemble_stats()

        if _init_setup_model:
            self._warn_about_images()
            self._setup_model()

    @staticmethod
    def _resolve_settings(
        n_heads: int,
        n_actor_heads: int | None,
        n_critic_heads: int | None,
        preset: str | None,
        confidence: str | ConfidenceStrategy | None,
        mask_prob: float | None,
    ) -> dict[str, Any]:
        """Head counts, confidence and mask probability from the explicit arguments and the preset."""
        n_heads = check_int("n_heads", n_heads, 1, "number of bootstrapped heads K")
        n_actor_heads = None if n_actor_heads is None else check_int("n_actor_heads", n_actor_heads, 1, "or None: n_heads")
        n_critic_heads = None if n_critic_heads is None else check_int("n_critic_heads", n_critic_heads, 1, "or None: n_heads")
        if confidence is not None:
            check_strategy(confidence)
        given = dict(n_actor_heads=n_actor_heads, n_critic_heads=n_critic_heads, confidence=confidence, mask_prob=mask_prob)
        settings: dict[str, Any] = dict(n_actor_heads=n_heads, n_critic_heads=n_heads, confidence="adaptive", mask_prob=0.5)
        if preset is not None:
            preset = normalize_preset_name(preset)
            for key, value in resolve_preset(preset, n_heads).items():
                explicit = given[key]
                if isinstance(explicit, str):
                    explicit = explicit.lower()
                if explicit is not None and key != "mask_prob" and explicit != value:
                    raise ValueError(f"preset={preset!r} sets {key}={value!r}, but {key}={given[key]!r} was given: drop one")
                settings[key] = value
        settings.update({key: value for key, value in given.items() if value is not None})
        if isinstance(settings["confidence"], str):
            settings["confidence"] = settings["confidence"].lower()
        n_actor, n_critic = settings["n_actor_heads"], settings["n_critic_heads"]
        if n_actor != n_critic and min(n_actor, n_critic) > 1:
            raise ValueError(
                "actor head k is paired with critic head k: n_actor_heads and n_critic_heads must be equal or one of them 1, "
                f"got n_actor_heads={n_actor}, n_critic_heads={n_critic}"
            )
        check_mask_args(max(n_actor, n_critic), settings["mask_prob"])
        settings["mask_prob"] = float(settings["mask_prob"])
        settings["preset"] = preset
        settings["n_heads"] = n_heads
        return settings

    @staticmethod
    def _check_arguments(**kwargs: Any) -> dict[str, Any]:
        """
        Check the given arguments (any subset of the constructor's, see ``_ARGUMENT_CHECKS``); each error names the
        parameter and the accepted values.

        :return: the values, numbers converted to Python ``int``/``float``/``bool``
        """
        checked = dict(kwargs)
        for name, value in kwargs.items():
            check = _ARGUMENT_CHECKS.get(name)
            if check is not None:
                checked[name] = check(name, value)
        return checked

    @classmethod
    def preset_names(cls) -> list[str]:
        """Names accepted by :meth:`preset` and the ``preset`` argument."""
        from sb3_soup.presets import PRESETS

        return sorted(PRESETS)

    @classmethod
    def preset(cls: type[SelfSOUP], name: str, policy: str | type[SOUPPolicy], env: GymEnv | str, **kwargs: Any) -> SelfSOUP:
        """
        One of the paper's models (Figure 1): ``SOUP.preset("dbddpg", "MlpPolicy", env, n_heads=5)``
        is ``SOUP("MlpPolicy", env, n_heads=5, preset="dbddpg")``.

        :param name: "ddpg", "ma_bddpg", "multi_ddpg", "dbddpg" or "soup"
        :param policy: the policy (see :class:`SOUP`)
        :param env: the environment (see :class:`SOUP`)
        :param kwargs: any other argument of :class:`SOUP`
        """
        return cls(policy, env, preset=name, **kwargs)

    def _get_policy_from_name(self, policy_name: str) -> type[BasePolicy]:
        if policy_name not in self.policy_aliases:
            hint = ""
            if policy_name == "CnnPolicy":
                hint = " (for images: MlpPolicy with policy_kwargs=dict(features_extractor_class=NatureCNN))"
            raise ValueError(
                f"policy must be one of {sorted(self.policy_aliases)} or a sb3_soup.SOUPPolicy subclass, "
                f"got {policy_name!r}{hint}"
            )
        return self.policy_aliases[policy_name]

    def _check_policy_and_spaces(self) -> None:
        """What SB3's checks let through but SOUP refuses: other policies, unknown policy_kwargs, MultiInputPolicy on Box."""
        if not (isinstance(self.policy_class, type) and issubclass(self.policy_class, SOUPPolicy)):
            raise ValueError(
                f"policy must be one of {sorted(self.policy_aliases)} or a sb3_soup.SOUPPolicy subclass, "
                f"got {self.policy_class!r}"
            )
        accepted = inspect.signature(self.policy_class.__init__).parameters
        if not any(parameter.kind == inspect.Parameter.VAR_KEYWORD for parameter in accepted.values()):
            set_by_soup = {"n_actor_heads", "n_critic_heads", "confidence", "confidence_kwargs"}
            names = sorted(set(accepted) - {"self", "observation_space", "action_space", "lr_schedule"} - set_by_soup)
            unknown = sorted(set(self.policy_kwargs) - set(names) - set_by_soup)
            if unknown:
                raise ValueError(f"policy_kwargs has unknown keys {unknown}; {self.policy_class.__name__} accepts {names}")
        if issubclass(self.policy_class, MultiInputPolicy) and not isinstance(self.observation_space, spaces.Dict):
            raise ValueError(
                f"policy must be 'MlpPolicy' for {self.observation_space} observations ('MultiInputPolicy' is for Dict)"
            )

    def _warn_about_images(self) -> None:
        extractor = self.policy_kwargs.get("features_extractor_class", FlattenExtractor)
        if is_image_space(self.observation_space, check_channels=False) and extractor is FlattenExtractor:
            warnings.warn(
                f"the observations are images {self.observation_space.shape}: MlpPolicy flattens their pixels (scaled to "
                "[0, 1]) into the MLP, as SB3's DDPG does. For a CNN pass "
                "policy_kwargs=dict(features_extractor_class=stable_baselines3.common.torch_layers.NatureCNN)",
                UserWarning,
                stacklevel=3,
            )

    def _setup_model(self) -> None:
        self._check_policy_and_spaces()
        if self.replay_buffer_class is None:
            self.replay_buffer_class = (
                BootstrappedDictReplayBuffer if isinstance(self.observation_space, spaces.Dict) else BootstrappedReplayBuffer
            )
        elif not (
            isinstance(self.replay_buffer_class, type)
            and issubclass(self.replay_buffer_class, (BootstrappedReplayBuffer, BootstrappedDictReplayBuffer))
        ):
            raise ValueError(
                "replay_buffer_class must be None or a subclass of sb3_soup.BootstrappedReplayBuffer or "
                f"BootstrappedDictReplayBuffer (SOUP needs the bootstrap masks), got {self.replay_buffer_class!r}"
            )
        self.replay_buffer_kwargs.update(n_masks=max(self.n_actor_heads, self.n_critic_heads), mask_prob=self.mask_prob)
        super()._setup_model()
        self._create_aliases()
        self.critic_lr_schedule = _as_schedule(self.critic_learning_rate)
        update_learning_rate(self.critic.optimizer, self.critic_lr_schedule(1))
        self._update_exploration_std()

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.actor_target = self.policy.actor_target
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target

    # ----- acting -----------------------------------------------------------------------------------------------

    def _update_exploration_std(self) -> None:
        """Gaussian noise std after ``num_timesteps`` env-steps: ``max(noise_std_min, noise_std * noise_decay ** t)``."""
        self.exploration_std = max(self.noise_std_min, self.noise_std * self.noise_decay**self.num_timesteps)
        self.policy.exploration_std = self.exploration_std

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """E-action of the ensemble for every env (eq. 7), plus exploration noise; random actions during warm-up."""
        if self.num_timesteps < learning_starts:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        assert self._last_obs is not None, "self._last_obs was not set"
        obs_tensor, _ = self.policy.obs_to_tensor(self._last_obs)
        with th.no_grad():
            selection = self.policy.select(obs_tensor, explore=True)
        self._record_selection(obs_tensor, selection)
        scaled_action = selection.actions.cpu().numpy()  # (n_envs, A) in [-1, 1]
        if action_noise is not None:
            noise = action_noise()
        else:
            noise = np.random.normal(0.0, self.exploration_std, size=scaled_action.shape)
        scaled_action = np.clip(scaled_action + noise, -1.0, 1.0)
        return self.policy.unscale_action(scaled_action), scaled_action

    def _record_selection(self, obs: PyTorchObs, selection: Selection) -> None:
        """Keep what the confidence strategy learns from, and the ensemble statistics to log."""
        if self.check_finite:
            self._check_selection(selection)
        self._selection_counts += np.bincount(selection.chosen.cpu().numpy(), minlength=self.n_actor_heads)
        self._n_selections += len(selection.chosen)
        if selection.q_matrix is None or selection.weights is None:
            return
        q_matrix = selection.q_matrix  # (B, Kc, Ka)
        if self.policy.confidence.needs_rollout and self.gradient_steps != 0:  # no training round would consume it
            self._pending_selection = (obs, q_matrix, selection.chosen)
        weights = selection.weights.expand_as(q_matrix)
        heads = th.arange(self.n_critic_heads, device=q_matrix.device)
        # confidence of critic head i in "its" candidate (candidate i, or the only one)
        own = weights[:, heads, heads.clamp(max=self.n_actor_heads - 1)]  # (B, Kc)
        self._confidence_sum += own.sum(dim=0).cpu().numpy()
        if self.n_critic_heads > 1:
            chosen_q = q_matrix.gather(2, selection.chosen.view(-1, 1, 1).expand(-1, self.n_critic_heads, 1))  # (B, Kc, 1)
            self._q_spread_sum += float(chosen_q.std(dim=1).sum())

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        if self.check_finite:
            for name, value in (("observation", new_obs), ("reward", reward)):
                if not _all_finite(value):
                    raise ValueError(
                        f"non-finite {name} (NaN or inf) returned by the environment at step {self.num_timesteps}: {value!r}. "
                        "Fix the environment, wrap it in VecCheckNan to locate the cause, or pass check_finite=False"
                    )
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        if self._pending_selection is not None:
            obs, q_matrix, chosen = self._pending_selection
            rewards = th.as_tensor(np.asarray(reward, dtype=np.float32), device=self.device)
            self._confidence_rollout.append((obs, q_matrix, chosen, rewards))
            self._pending_selection = None
        # Algorithm 1: every episode starts with a randomly selected head pair
        assert self._active_heads is not None
        for env_idx in np.flatnonzero(dones):
            self._active_heads[env_idx] = np.random.randint(self.policy.n_pairs)

    def _on_step(self) -> None:
        self.policy.confidence.on_step(self.n_envs)
        self._update_exploration_std()

    # ----- training ---------------------------------------------------------------------------------------------

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        # Switch to train mode (this affects batch norm / dropout)
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer])
        critic_lr = self.critic_lr_schedule(self._current_progress_remaining)
        update_learning_rate(self.critic.optimizer, critic_lr)

        critic_losses, actor_losses = [], []
        for _ in range(gradient_steps):
            self._n_updates += 1
            data: Samples = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr,assignment]
            critic_value, actor_value = self._gradient_step(data)
            critic_losses += critic_value
            actor_losses += actor_value

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/critic_learning_rate", critic_lr)
        self.logger.record("train/noise_std", self.exploration_std)
        if critic_losses:
            self.logger.record("train/critic_loss", np.mean(critic_losses))
        if actor_losses:
            self.logger.record("train/actor_loss", np.mean(actor_losses))
        for key, value in self._update_confidence().items():
            self.logger.record(f"train/{key}", value)

    def _gradient_step(self, data: Samples) -> tuple[list[float], list[float]]:
        """
        One gradient step of the training scheme on a minibatch: the critic heads of the trained pairs (eqs. 3-4), then,
        every ``policy_delay`` steps, their actor heads (eq. 5) and the soft update of the targets (eq. 6).

        :return: the critic loss and the actor loss, each as a list of zero or one value
        """
        masks = data.masks.T.unsqueeze(-1).float()  # (P, B, 1)
        critic_pairs, actor_pairs = self._training_pairs(masks)
        if not critic_pairs:
            return [], []  # this minibatch holds nothing for the heads to train

        with th.no_grad():
            next_q = self._next_q(data.next_observations, critic_pairs)  # (H, B, 1)
            target_q = td_target(data.rewards, data.dones, self.gamma, next_q)  # eq. 4
        critic_heads = self.policy.critic_heads(critic_pairs)
        current_q = self.critic(data.observations, data.actions, head=critic_heads.head_arg, grad_scale=critic_heads.scale)
        per_pair = critic_loss(current_q, target_q, self._pair_masks(masks, critic_pairs))  # (H,), eq. 3
        critic_value = self._optimize(self.critic, per_pair, critic_heads, critic_pairs, "critic_loss")
        if self._n_updates % self.policy_delay != 0 or not actor_pairs:
            return [critic_value], []

        actor_heads, scoring_heads = self.policy.actor_heads(actor_pairs), self.policy.critic_heads(actor_pairs)
        actions_pi = self.actor(data.observations, head=actor_heads.head_arg, grad_scale=actor_heads.scale)  # (H, B, A)
        q_pi = self.critic(data.observations, actions_pi, head=scoring_heads.head_arg)  # (H, B, 1)
        per_pair = actor_loss(q_pi, self._pair_masks(masks, actor_pairs))  # (H,), eq. 5
        actor_value = self._optimize(self.actor, per_pair, actor_heads, actor_pairs, "actor_loss")
        soft_update(self.actor, self.actor_target, self.tau, actor_heads.rows)  # eq. 6
        soft_update(self.critic, self.critic_target, self.tau, critic_heads.rows)
        return [critic_value], [actor_value]

    def _training_pairs(self, masks: th.Tensor) -> tuple[list[int], list[int]]:
        """
        The training scheme: which head pairs this minibatch trains, as (critic pairs, actor pairs). "active": the pair
        drawn for the episode (Algorithm 1; with n_envs > 1 the gradient steps take the envs' pairs in turn); "all": every
        pair; "all_critics": every critic head, the active pair's actor head. A pair whose mask keeps none of the
        minibatch is left out.

        :param masks: ``(P, B, 1)`` bootstrap masks of the minibatch
        """
        assert self._active_heads is not None
        active = [int(self._active_heads[(self._n_updates - 1) % len(self._active_heads)])]
        every = list(range(self.policy.n_pairs))
        critic_pairs = active if self.train_heads == "active" else every
        actor_pairs = every if self.train_heads == "all" else active
        has_data = masks.sum(dim=(1, 2)) > 0  # (P,)
        if bool(has_data.all()):
            return critic_pairs, actor_pairs
        kept = has_data.tolist()
        return [pair for pair in critic_pairs if kept[pair]], [pair for pair in actor_pairs if kept[pair]]

    @staticmethod
    def _pair_masks(masks: th.Tensor, pairs: list[int]) -> th.Tensor:
        """The masks ``(H, B, 1)`` of ``pairs`` among all pairs' ``(P, B, 1)``."""
        return masks if len(pairs) == len(masks) else masks[pairs]

    def _next_q(self, next_observations: PyTorchObs, pairs: list[int]) -> th.Tensor:
        """
        Each pair's value of the next state, which eq. 4 bootstraps from: its target critic head at its target actor head's
        action (the paper). With ``target_policy_noise`` the action is smoothed with clipped Gaussian noise (TD3); with
        ``target_q="min_pair"`` the value is the smaller of its own target critic head's and one random other's (the
        clipped double Q of TD3 across the ensemble, as REDQ).

        :return: ``(H, B, 1)``
        """
        actor_heads, critic_heads = self.policy.actor_heads(pairs), self.policy.critic_heads(pairs)
        next_actions = self.actor_target(next_observations, head=actor_heads.head_arg)  # (H or 1, B, A)
        if self.target_policy_noise > 0:
            clip = self.target_noise_clip
            noise = (th.randn_like(next_actions) * self.target_policy_noise).clamp(-clip, clip)
            next_actions = (next_actions + noise).clamp(-1.0, 1.0)
        features = self.critic_target.body_features(next_observations, next_actions)  # (H or 1, B, F)
        next_q = self.critic_target.heads(features, critic_heads.head_arg)  # (H, B, 1)
        if self.target_q == "min_pair" and self.n_critic_heads > 1:
            own = th.as_tensor(critic_heads.per_pair, device=self.device)  # (H,)
            others = (own + th.randint(1, self.n_critic_heads, own.shape, device=self.device)) % self.n_critic_heads
            next_q = th.minimum(next_q, self.critic_target.heads(features, others))
        return next_q

    def _check_loss(self, name: str, value: float, where: Callable[[], str]) -> None:
        """
        The one place where training stops on a non-finite loss (when ``check_finite``): costs a ``math.isfinite``
        on a loss already fetched for logging; ``where`` is only called once a value is non-finite.

        :param name: the loss ("critic_loss", "actor_loss", "confidence_loss")
        :param value: its value
        :param where: says what the loss trained (which head pairs, the confidence strategy)
        """
        if not self.check_finite or math.isfinite(value):
            return
        raise FloatingPointError(
            f"non-finite {name} ({value}) for {where()} at update {self._n_updates} (step {self.num_timesteps}): the Q "
            "values or their targets diverged. This update was applied, so the model's parameters may be non-finite too: "
            "resume from an earlier checkpoint with lower learning rates or a rescaled reward, or pass check_finite=False "
            "to train on anyway"
        )

    def _check_selection(self, selection: Selection) -> None:
        """
        Stop at the first non-finite E-action, Q value or confidence weight met while acting (when ``check_finite``):
        one fused check on tensors already computed, the heads are only worked out once something is non-finite.
        """
        finite = th.isfinite(selection.actions).all()
        if selection.q_matrix is not None and selection.weights is not None:
            finite = finite & th.isfinite(selection.q_matrix).all() & th.isfinite(selection.weights).all()
        if bool(finite):
            return
        problems = []
        if selection.q_matrix is not None:
            bad = ~th.isfinite(selection.q_matrix)  # (B, Kc, Ka)
            bad_candidates = bad.all(dim=1).any(dim=0)  # (Ka,): every critic head gave a non-finite Q to this candidate
            bad_critics = (bad & ~bad_candidates.view(1, 1, -1)).any(dim=2).any(dim=0)  # (Kc,): the other non-finite Qs
            if bool(bad_candidates.any()):
                heads = th.nonzero(bad_candidates).flatten().tolist()
                problems.append(f"every critic head gave a non-finite Q value to the candidate(s) of actor head(s) {heads}")
            if bool(bad_critics.any()):
                problems.append(f"critic head(s) {th.nonzero(bad_critics).flatten().tolist()} gave non-finite Q values")
        if selection.weights is not None and not bool(th.isfinite(selection.weights).all()):
            problems.append(f"the confidence strategy {type(self.policy.confidence).__name__} gave non-finite weights")
        bad_envs = ~th.isfinite(selection.actions).all(dim=1)
        if bool(bad_envs.any()):
            heads = sorted(set(selection.chosen[bad_envs].tolist()))
            problems.append(f"actor head(s) {heads} proposed non-finite actions")
        raise FloatingPointError(
            f"non-finite values while acting at step {self.num_timesteps}: {'; '.join(problems)}. Resume from an earlier "
            "checkpoint (with lower learning rates or a rescaled reward), or pass check_finite=False to act on anyway"
        )

    def _optimize(
        self, model: EnsembleActor | EnsembleCritic, per_pair: th.Tensor, heads: TrainedHeads, pairs: list[int], name: str
    ) -> float:
        """
        One gradient step on ``model`` alone (the actor loss leaves no gradient in the critic) for the pairs' losses: each
        head gets the gradient of its own loss (the mean over the pairs when one head serves them all), and the body,
        whose gradient is scaled by ``heads.scale``, the mean over its heads. The heads left out keep their values and
        their Adam state (see EnsembleAdam).

        :return: the loss, checked to be finite (``check_finite``)
        """
        loss = per_pair.sum() * heads.n_heads / len(pairs)
        optimizer = model.optimizer
        optimizer.zero_grad()
        loss.backward(inputs=model.all_parameters())
        if isinstance(optimizer, EnsembleAdam):
            optimizer.step(head=heads.rows)
        else:
            optimizer.step()
        value = loss.item()
        self._check_loss(name, value, lambda: self.policy.describe_pairs(pairs, per_pair))
        return value

    def _update_confidence(self) -> dict[str, float]:
        """One update of the confidence strategy on the selections made since the last one (all envs)."""
        if not self._confidence_rollout:
            return {}
        observations, q_matrices, chosen, rewards = zip(*self._confidence_rollout)
        self._confidence_rollout = []
        if isinstance(observations[0], dict):
            obs_batch: PyTorchObs = {key: th.cat([obs[key] for obs in observations]) for key in observations[0]}  # type: ignore[index]
        else:
            obs_batch = th.cat(observations)  # type: ignore[arg-type]
        rollout = ConfidenceRollout(obs_batch, th.cat(q_matrices), th.cat(chosen), th.cat(rewards))
        logs = check_update_logs(self.policy.confidence, self.policy.confidence.update(rollout))
        if "confidence_loss" in logs:
            strategy = type(self.policy.confidence).__name__
            self._check_loss("confidence_loss", logs["confidence_loss"], lambda: f"the {strategy}")
        return logs

    # ----- logging, saving --------------------------------------------------------------------------------------

    def _reset_ensemble_stats(self) -> None:
        self._selection_counts = np.zeros(self.n_actor_heads, dtype=np.int64)
        self._confidence_sum = np.zeros(self.n_critic_heads)
        self._q_spread_sum = 0.0
        self._n_selections = 0

    def dump_logs(self) -> None:
        """Log the ensemble statistics since the last dump, then SB3's usual rollout logs."""
        if self._n_selections > 0:
            for k, count in enumerate(self._selection_counts):
                self.logger.record(f"selection/head_{k}", count / self._n_selections)
            if self.n_actor_heads > 1 or self.n_critic_heads > 1:
                for i, total in enumerate(self._confidence_sum):
                    self.logger.record(f"confidence/head_{i}", total / self._n_selections)
            if self.n_critic_heads > 1:
                self.logger.record("rollout/q_spread", self._q_spread_sum / self._n_selections)
        self.logger.record("train/noise_std", self.exploration_std)
        self._reset_ensemble_stats()
        super().dump_logs()

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, Any]:
        resets_env = reset_num_timesteps or self._last_obs is None
        result = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        if self.check_finite and self._last_obs is not None and not _all_finite(self._last_obs):
            raise ValueError(
                f"non-finite observation (NaN or inf) returned by env.reset(): {self._last_obs!r}. "
                "Fix the environment, wrap it in VecCheckNan to locate the cause, or pass check_finite=False"
            )
        if resets_env or self._active_heads is None or len(self._active_heads) != self.n_envs:
            # new episodes: draw their head pairs; selections without their reward are dropped
            self._active_heads = np.random.randint(self.policy.n_pairs, size=self.n_envs)
            self._pending_selection = None
            self._confidence_rollout = []
        self._update_exploration_std()
        return result

    def learn(
        self: SelfSOUP,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "SOUP",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfSOUP:
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Iterable[str] | None = None,
        include: Iterable[str] | None = None,
    ) -> None:
        """
        Save all the attributes of the object and the model parameters in a zip-file, as SB3 does, plus the
        sb3-soup version and save format, and the random generators' states (restored by :meth:`load`).

        :param path: path to the file where the model should be saved
        :param exclude: name of parameters that should be excluded in addition to the default ones
        :param include: name of parameters that might be excluded but should be included anyway
        """
        self._rng_state = capture_rng_state(self.action_space)
        try:
            super().save(path, exclude, include)
        finally:
            del self._rng_state

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfSOUP],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfSOUP:
        """
        Load a model saved by :meth:`save` as it was saved (its head counts, preset, strategy and settings), after
        checking that the file is a complete SOUP model in a save format this version reads (see
        :mod:`sb3_soup.saving`). The random generators are put back in their state at save time (SB3 would reseed them
        with the model's seed), so that ``learn(..., reset_num_timesteps=False)`` continues the same random streams.

        :param path: path to the file (or a file-like) where to load the agent from
        :param env: the new environment to run the loaded model on (None: prediction only)
        :param device: Device on which the code should run
        :param custom_objects: objects to use instead of the saved ones (see SB3's ``load``)
        :param print_system_info: print the saved and the current system info
        :param force_reset: reset the environment before training (False: continue from the saved last observation,
            for an environment restored to the same state, see :mod:`sb3_soup.checkpoint`)
        :param kwargs: settings to change when loading (e.g. ``learning_starts``); the ones that shape the networks or
            the strategy (head counts, preset, confidence and its parameters) are fixed by the file
        :return: the model
        """
        data = read_saved_data(path)
        saved_format = check_saved_format(data, path)
        fixed = sorted(set(kwargs) & set(_STRUCTURAL_ARGUMENTS))
        if fixed:
            raise ValueError(
                f"{fixed} cannot be changed when loading: the saved model was built with "
                + ", ".join(f"{key}={data.get(key)!r}" for key in fixed if not isinstance(data.get(key), dict))
                + "; create a new SOUP to use other values"
            )
        kwargs = cls._check_arguments(**kwargs)
        try:
            model = super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)
        except ValueError as error:
            if "wasn't a zip-file" not in str(error):
                raise
            raise ValueError(f"{path} is a corrupt model zip ({error.__cause__}): load an earlier checkpoint") from error
        rng_state = model.__dict__.pop("_rng_state", None)
        if rng_state is not None:
            restore_rng_state(rng_state, model.action_space)
        elif saved_format == 0:
            warnings.warn(
                f"{path} was saved by sb3-soup 0.1.0a0 before the save format was stored: loaded as saved, but without the "
                "random generators' state (they are reseeded with the model's seed, as SB3 does)",
                UserWarning,
                stacklevel=2,
            )
        # From now on it is this version's model (and saved in this version's format)
        model._sb3_soup_format = SAVE_FORMAT_VERSION
        model._sb3_soup_version = __version__
        return model

    def set_parameters(
        self,
        load_path_or_dict: str | dict[str, Any],
        exact_match: bool = True,
        device: th.device | str = "auto",
    ) -> None:
        """
        Load parameters from a saved model (or a dict) into this model's networks, which must have their shapes;
        a model saved with other head counts or sizes is loaded with :meth:`load`, which builds it as saved.

        :param load_path_or_dict: the saved model, or a dict of state dicts
        :param exact_match: every parameter of this model must be set
        :param device: Device on which the code should run
        """
        try:
            super().set_parameters(load_path_or_dict, exact_match, device)
        except RuntimeError as error:
            mismatches = [line.strip() for line in str(error).splitlines() if "size mismatch" in line]
            if not mismatches:
                raise
            raise ValueError(
                f"the saved parameters do not fit this model's networks (other head counts or net_arch?): {mismatches[0]} "
                f"({len(mismatches)} mismatches). SOUP.load builds a model as it was saved"
            ) from error

    def load_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """
        Load a replay buffer saved by ``save_replay_buffer``, after checking that it fits this model (bootstrap masks for
        each head pair, same number of envs). The model's buffer is only replaced when the file is complete and fits.

        :param path: Path to the pickled replay buffer
        :param truncate_last_traj: unused (SB3 uses it for ``HerReplayBuffer``, which SOUP does not support)
        """
        try:
            buffer = load_from_pkl(path, self.verbose)
        except OSError:
            raise
        except Exception as error:
            raise ValueError(
                f"could not read the replay buffer {path}: the file is truncated or corrupt (a process killed while writing "
                f"it leaves such files): {type(error).__name__}: {error}"
            ) from error
        if not isinstance(buffer, (BootstrappedReplayBuffer, BootstrappedDictReplayBuffer)):
            raise ValueError(
                f"{path} holds a {type(buffer).__name__}, not a sb3_soup BootstrappedReplayBuffer or "
                "BootstrappedDictReplayBuffer (SOUP needs the bootstrap masks)"
            )
        if buffer.n_masks != self.policy.n_pairs:
            raise ValueError(
                f"the replay buffer in {path} has bootstrap masks for {buffer.n_masks} head pairs, this model has "
                f"{self.policy.n_pairs} (n_actor_heads={self.n_actor_heads}, n_critic_heads={self.n_critic_heads})"
            )
        if buffer.n_envs != self.n_envs:
            raise ValueError(f"the replay buffer in {path} was filled by {buffer.n_envs} envs, this model has {self.n_envs}")
        buffer.device = self.device
        self.replay_buffer = buffer

    def _excluded_save_params(self) -> list[str]:
        # Exclude aliases
        return [*super()._excluded_save_params(), "actor", "actor_target", "critic", "critic_target"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        if self.policy.confidence.optimizer is not None:
            state_dicts.append("policy.confidence.optimizer")
        return state_dicts, []
