"""SOUP: Self-Adaptive Double Bootstrapped DDPG, as a Stable-Baselines3 off-policy algorithm."""

import math
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
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
from sb3_soup.confidence import CONFIDENCE_STRATEGIES, ConfidenceRollout, ConfidenceStrategy
from sb3_soup.networks import EnsembleActor, EnsembleCritic
from sb3_soup.optim import EnsembleAdam
from sb3_soup.policies import MlpPolicy, MultiInputPolicy, Selection, SOUPPolicy, soft_update
from sb3_soup.presets import normalize_preset_name, resolve_preset

SelfSOUP = TypeVar("SelfSOUP", bound="SOUP")
Samples = BootstrappedReplayBufferSamples | BootstrappedDictReplayBufferSamples

TRAIN_HEADS = ("active", "all")


def _check_int(name: str, value: Any, minimum: int = 1) -> None:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


def _check_float(name: str, value: Any, low: float, high: float, low_open: bool, high_open: bool, meaning: str) -> None:
    ok = isinstance(value, (int, float, np.floating)) and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        ok = (value > low if low_open else value >= low) and (value < high if high_open else value <= high)
    if not ok:
        interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
        raise ValueError(f"{name} must be a float in {interval} ({meaning}), got {value!r}")


def _all_finite(value: np.ndarray | dict[str, np.ndarray]) -> bool:
    if isinstance(value, dict):
        return all(_all_finite(item) for item in value.values())
    array = np.asarray(value)
    return not np.issubdtype(array.dtype, np.floating) or bool(np.isfinite(array).all())


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
        (default, or the preset's) or a :class:`sb3_soup.ConfidenceStrategy` instance
    :param alpha: fixed confidence of a critic head in its own candidate (``confidence="fixed"``), in (0, 1)
    :param decay: per-step decay of the confidence (``confidence="decayed"``), in (0, 1]
    :param temperature: softmax temperature of the selection policy trained by REINFORCE (``"adaptive"``), > 0
    :param confidence_lr: learning rate of the confidence network (``"adaptive"``)
    :param confidence_baseline: subtract a running-mean reward baseline in REINFORCE (False: the paper's raw reward)
    :param mask_prob: probability that a head sees a transition (Bernoulli masks), in (0, 1]; 1 turns bootstrap off
        (default 0.5, 1.0 for the "ddpg" preset)
    :param train_heads: "active": train the episode's active head pair (the paper); "all": every head pair
        on each minibatch, each with its own masked loss (Bootstrapped DQN style)
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
        mask_prob: float | None = None,
        train_heads: str = "active",
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
        self._check_arguments(
            alpha=alpha,
            decay=decay,
            temperature=temperature,
            confidence_lr=confidence_lr,
            confidence_baseline=confidence_baseline,
            train_heads=train_heads,
            noise_std=noise_std,
            noise_decay=noise_decay,
            noise_std_min=noise_std_min,
            check_finite=check_finite,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
        )
        policy_kwargs = dict(policy_kwargs or {})
        reserved = {"n_actor_heads", "n_critic_heads", "confidence", "confidence_kwargs"} & set(policy_kwargs)
        if reserved:
            raise ValueError(f"set {sorted(reserved)} as SOUP arguments, not in policy_kwargs")

        super().__init__(
            policy,
            env,
            learning_rate,
            buffer_size,
            learning_starts,
            batch_size,
            tau,
            gamma,
            train_freq,
            gradient_steps,
            action_noise=action_noise,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            sde_support=False,
            supported_action_spaces=(spaces.Box,),
            support_multi_env=True,
        )
        self.critic_learning_rate = critic_learning_rate
        self.n_heads = n_heads
        self.preset_name: str | None = settings["preset"]
        self.n_actor_heads: int = settings["n_actor_heads"]
        self.n_critic_heads: int = settings["n_critic_heads"]
        self.confidence = settings["confidence"]
        self.mask_prob: float = settings["mask_prob"]
        self.alpha = alpha
        self.decay = decay
        self.temperature = temperature
        self.confidence_lr = confidence_lr
        self.confidence_baseline = confidence_baseline
        self.train_heads = train_heads
        self.noise_std = noise_std
        self.noise_decay = noise_decay
        self.noise_std_min = noise_std_min
        self.check_finite = check_finite
        self.exploration_std = noise_std

        self.policy_kwargs.update(
            n_actor_heads=self.n_actor_heads,
            n_critic_heads=self.n_critic_heads,
            confidence=self.confidence,
            confidence_kwargs=dict(
                alpha=alpha, decay=decay, lr=confidence_lr, temperature=temperature, baseline=confidence_baseline
            ),
        )
        # Per env: the head pair trained during its current episode (drawn at each episode start)
        self._active_heads: np.ndarray | None = None
        # Selections made while acting, kept for on-policy confidence strategies until the next update
        self._pending_selection: tuple[PyTorchObs, th.Tensor, th.Tensor] | None = None
        self._confidence_rollout: list[tuple[PyTorchObs, th.Tensor, th.Tensor, th.Tensor]] = []
        self._reset_ensemble_stats()

        if _init_setup_model:
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
        _check_int("n_heads", n_heads)
        for name, value in (("n_actor_heads", n_actor_heads), ("n_critic_heads", n_critic_heads)):
            if value is not None:
                _check_int(name, value)
        if isinstance(confidence, str) and confidence.lower() not in CONFIDENCE_STRATEGIES:
            raise ValueError(
                f"confidence must be one of {CONFIDENCE_STRATEGIES} or a ConfidenceStrategy instance, got {confidence!r}"
            )
        if confidence is not None and not isinstance(confidence, (str, ConfidenceStrategy)):
            raise ValueError(
                f"confidence must be one of {CONFIDENCE_STRATEGIES} or an instance of sb3_soup.ConfidenceStrategy "
                f"(implementing weights(obs, q_matrix) -> W), got {confidence!r} of type {type(confidence).__name__}"
            )
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
        return settings

    @staticmethod
    def _check_arguments(**kwargs: Any) -> None:
        _check_float("alpha", kwargs["alpha"], 0.0, 1.0, True, True, "fixed confidence of a head in its own candidate")
        _check_float("decay", kwargs["decay"], 0.0, 1.0, True, False, "per-step decay of the decayed confidence")
        _check_float("temperature", kwargs["temperature"], 0.0, math.inf, True, True, "softmax temperature of the selection")
        _check_float("confidence_lr", kwargs["confidence_lr"], 0.0, math.inf, True, True, "confidence network learning rate")
        _check_float("noise_std", kwargs["noise_std"], 0.0, math.inf, False, True, "initial exploration noise std")
        _check_float("noise_decay", kwargs["noise_decay"], 0.0, 1.0, True, False, "noise std decay per env step")
        _check_float("noise_std_min", kwargs["noise_std_min"], 0.0, math.inf, False, True, "lowest exploration noise std")
        _check_float("tau", kwargs["tau"], 0.0, 1.0, True, False, "soft update coefficient")
        _check_float("gamma", kwargs["gamma"], 0.0, 1.0, False, False, "discount factor")
        _check_int("batch_size", kwargs["batch_size"])
        for name in ("confidence_baseline", "check_finite"):
            if not isinstance(kwargs[name], (bool, np.bool_)):
                raise ValueError(f"{name} must be True or False, got {kwargs[name]!r}")
        if kwargs["train_heads"] not in TRAIN_HEADS:
            raise ValueError(f"train_heads must be one of {TRAIN_HEADS}, got {kwargs['train_heads']!r}")

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

    def _setup_model(self) -> None:
        if self.replay_buffer_class is None:
            self.replay_buffer_class = (
                BootstrappedDictReplayBuffer if isinstance(self.observation_space, spaces.Dict) else BootstrappedReplayBuffer
            )
        elif not issubclass(self.replay_buffer_class, (BootstrappedReplayBuffer, BootstrappedDictReplayBuffer)):
            raise ValueError(
                "replay_buffer_class must be a subclass of sb3_soup.BootstrappedReplayBuffer or BootstrappedDictReplayBuffer "
                f"(SOUP needs the bootstrap masks), got {self.replay_buffer_class.__name__}"
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
            selection = self.policy.select(obs_tensor)
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
        assert self._active_heads is not None

        critic_losses, actor_losses = [], []
        for gradient_step in range(gradient_steps):
            replay_data: Samples = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr,assignment]
            if self.train_heads == "active":
                # n_envs > 1: the gradient steps take the envs' active pairs in turn
                pair = int(self._active_heads[(self._n_updates + gradient_step) % len(self._active_heads)])
                losses = self._train_pair(replay_data, pair)
            else:
                losses = self._train_all_pairs(replay_data)
            if losses is not None:
                critic_losses.append(losses[0])
                actor_losses.append(losses[1])
        self._n_updates += gradient_steps

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/critic_learning_rate", critic_lr)
        self.logger.record("train/noise_std", self.exploration_std)
        if critic_losses:
            self.logger.record("train/critic_loss", np.mean(critic_losses))
            self.logger.record("train/actor_loss", np.mean(actor_losses))
        for key, value in self._update_confidence().items():
            self.logger.record(f"train/{key}", value)

    def _check_loss(self, name: str, value: float, pair: int | None) -> None:
        if self.check_finite and not math.isfinite(value):
            which = "every head pair" if pair is None else f"head pair {pair}"
            raise FloatingPointError(
                f"non-finite {name} ({value}) for {which} at update {self._n_updates}: the Q values or targets diverged. "
                "Lower the learning rates, check the reward scale, or pass check_finite=False to train on anyway"
            )

    def _train_pair(self, data: Samples, pair: int) -> tuple[float, float] | None:
        """
        Paper mode (Algorithm 1): one DDPG step for the active pair (actor head, critic head) on the transitions
        its mask keeps. Gradients reach the shared bodies through this pair only; other heads are left untouched.
        """
        actor_head, critic_head = self.policy.pair_heads(pair)
        masks = data.masks[:, pair].unsqueeze(1).float()  # (B, 1)
        n_kept = masks.sum()
        if n_kept.item() == 0:
            return None  # this minibatch holds nothing for this head
        with th.no_grad():
            next_actions = self.actor_target(data.next_observations, head=actor_head)  # (B, A)
            next_q = self.critic_target(data.next_observations, next_actions, head=critic_head)  # (B, 1)
            target_q = data.rewards + (1 - data.dones) * self.gamma * next_q  # (B, 1), eq. 4

        current_q = self.critic(data.observations, data.actions, head=critic_head)  # (B, 1)
        critic_loss = (masks * (target_q - current_q) ** 2).sum() / n_kept  # eq. 3, masked
        self._optimize(self.critic, critic_loss, critic_head)

        actions_pi = self.actor(data.observations, head=actor_head)  # (B, A)
        actor_loss = -(masks * self.critic(data.observations, actions_pi, head=critic_head)).sum() / n_kept  # eq. 5
        self._optimize(self.actor, actor_loss, actor_head)

        soft_update(self.actor, self.actor_target, self.tau, head=actor_head)  # eq. 6
        soft_update(self.critic, self.critic_target, self.tau, head=critic_head)
        critic_value, actor_value = critic_loss.item(), actor_loss.item()
        self._check_loss("critic_loss", critic_value, pair)
        self._check_loss("actor_loss", actor_value, pair)
        return critic_value, actor_value

    def _train_all_pairs(self, data: Samples) -> tuple[float, float] | None:
        """
        Every pair on the same minibatch in one batched pass, each with its own masked loss. A shared body gets
        the mean of the gradients of the heads above it, a head its own (a single head serving every pair, the mean).
        """
        n_pairs, n_actor, n_critic = self.policy.n_pairs, self.n_actor_heads, self.n_critic_heads
        masks = data.masks.T.unsqueeze(-1).float()  # (P, B, 1)
        n_kept = masks.sum(dim=1, keepdim=True)  # (P, 1, 1)
        has_data = n_kept.view(-1) > 0  # (P,)
        if not bool(has_data.any()):
            return None
        n_kept = n_kept.clamp(min=1)
        with th.no_grad():
            next_actions = self.actor_target(data.next_observations)  # (Ka, B, A)
            next_q = self.critic_target(data.next_observations, next_actions)  # (P, B, 1): head k scores actor head k
            target_q = data.rewards + (1 - data.dones) * self.gamma * next_q  # (P, B, 1)

        current_q = self.critic(data.observations, data.actions, grad_scale=1 / n_critic)  # (Kc, B, 1)
        per_pair = (masks * (target_q - current_q) ** 2).sum(dim=1) / n_kept.view(-1, 1)  # (P, 1)
        critic_loss = per_pair.sum() * n_critic / n_pairs
        self._optimize(self.critic, critic_loss, None if bool(has_data.all()) else has_data[:n_critic])

        actions_pi = self.actor(data.observations, grad_scale=1 / n_actor)  # (Ka, B, A)
        q_pi = self.critic(data.observations, actions_pi)  # (P, B, 1)
        actor_loss = -((masks * q_pi).sum(dim=1) / n_kept.view(-1, 1)).sum() * n_actor / n_pairs
        self._optimize(self.actor, actor_loss, None if bool(has_data.all()) else has_data[:n_actor])

        soft_update(self.actor, self.actor_target, self.tau)
        soft_update(self.critic, self.critic_target, self.tau)
        critic_value, actor_value = critic_loss.item(), actor_loss.item()
        self._check_loss("critic_loss", critic_value, None)
        self._check_loss("actor_loss", actor_value, None)
        return critic_value, actor_value

    @staticmethod
    def _optimize(model: EnsembleActor | EnsembleCritic, loss: th.Tensor, head: int | th.Tensor | None) -> None:
        """Gradient step on ``model`` alone (the actor loss leaves no gradient in the critic); ``head``: see EnsembleAdam."""
        optimizer = model.optimizer
        optimizer.zero_grad()
        loss.backward(inputs=list(model.parameters()))
        if isinstance(optimizer, EnsembleAdam):
            optimizer.step(head=head)
        else:
            optimizer.step()

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
        logs = self.policy.confidence.update(rollout)
        if "confidence_loss" in logs:
            self._check_loss("confidence_loss", logs["confidence_loss"], None)
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

    def _excluded_save_params(self) -> list[str]:
        # Exclude aliases
        return [*super()._excluded_save_params(), "actor", "actor_target", "critic", "critic_target"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        if self.policy.confidence.optimizer is not None:
            state_dicts.append("policy.confidence.optimizer")
        return state_dicts, []
