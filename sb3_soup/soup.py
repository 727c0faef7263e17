"""SOUP: Self-Adaptive Double Bootstrapped DDPG, as a Stable-Baselines3 off-policy algorithm."""

import warnings
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, PyTorchObs, Schedule
from stable_baselines3.common.utils import update_learning_rate
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

try:  # SB3 >= 2.6
    from stable_baselines3.common.utils import FloatSchedule as _as_schedule
except ImportError:  # pragma: no cover
    from stable_baselines3.common.utils import get_schedule_fn as _as_schedule  # type: ignore[assignment]

from sb3_soup.arguments import ARGUMENT_RULES, check_arguments
from sb3_soup.buffers import (
    BootstrappedDictReplayBufferSamples,
    BootstrappedReplayBufferSamples,
    bootstrapped_buffer_class,
)
from sb3_soup.confidence import ConfidenceStep, ConfidenceStrategy, check_update_logs
from sb3_soup.diagnostics import EnsembleStats, check_loss, check_selection
from sb3_soup.loading import SAVE_FORMAT_VERSION, CheckedLoading, __version__
from sb3_soup.networks import EnsembleActor, EnsembleCritic, soft_update
from sb3_soup.noise import default_action_noise, noise_std
from sb3_soup.optim import EnsembleAdam
from sb3_soup.policies import (
    SET_BY_SOUP,
    CnnPolicy,
    MlpPolicy,
    MultiInputPolicy,
    Selection,
    SOUPPolicy,
    TrainedHeads,
    check_policy,
)
from sb3_soup.presets import resolve_model
from sb3_soup.validation import check_finite_env_output

SelfSOUP = TypeVar("SelfSOUP", bound="SOUP")
Samples = BootstrappedReplayBufferSamples | BootstrappedDictReplayBufferSamples


def masked_mean(values: th.Tensor, masks: th.Tensor) -> th.Tensor:
    """
    Mean of each head's values over the transitions its bootstrap mask keeps (Algorithm 1: "the i-th experience with
    mask m_i^k = 0 is ignored"): ``sum_j m_j v_j / max(1, sum_j m_j)``, 0 for a head whose mask keeps none.

    :param values: ``(H, B, 1)``
    :param masks: ``(H, B, 1)``, 1.0 where head h sees transition b
    :return: ``(H,)``
    """
    return ((masks * values).sum(dim=1) / masks.sum(dim=1).clamp(min=1)).squeeze(-1)


class SOUP(CheckedLoading):
    """
    Self-Adaptive Double Bootstrapped DDPG (SOUP), Zheng et al., IJCAI 2018: https://www.ijcai.org/proceedings/2018/0444.pdf

    DDPG with a bootstrapped actor and critic (shared bodies, K heads): every actor head proposes an action, every
    critic head scores every proposal, a confidence strategy weights the scores and the best-rated proposal is executed
    (eq. 7). Each gradient step trains every (actor head, critic head) pair on the transitions its bootstrap mask lets
    it see, with TD3's clipped double Q across the heads, target smoothing and delayed actor (the defaults, chosen on a
    suite of tasks: ``docs/results.md``); the paper's update, one randomly drawn pair per episode on its own target
    (Algorithm 1), is ``train_heads="active", target_q="own", policy_delay=1, target_policy_noise=0.0``
    (:func:`sb3_soup.paper_settings`). The paper's equations mapped to this code: ``docs/equations.md``.

    :param policy: The policy model to use (MlpPolicy, CnnPolicy, MultiInputPolicy)
    :param env: The environment to learn from (if registered in Gym, can be str)
    :param learning_rate: learning rate for Adam, of the actor and (unless ``critic_learning_rate`` is given) the
        critic; it can be a function of the current progress remaining (from 1 to 0)
    :param critic_learning_rate: the critic's own learning rate (float or schedule; the paper: 3e-4); None: the critic
        follows ``learning_rate``, as every optimizer of SB3's TD3 does
    :param buffer_size: size of the replay buffer
    :param learning_starts: how many steps to collect transitions for (uniformly random actions) before learning starts
    :param batch_size: Minibatch size for each gradient update
    :param tau: the soft update coefficient ("Polyak update", between 0 and 1)
    :param gamma: the discount factor
    :param train_freq: Update the model every ``train_freq`` steps, or a tuple like ``(5, "step")``, ``(2, "episode")``
    :param gradient_steps: How many gradient steps to do after each rollout (-1: as many as env steps)
    :param action_noise: an SB3 ``ActionNoise`` added to the E-action in the [-1, 1] action scale; None (unlike TD3):
        N(0, 0.1); the paper's decaying std: :class:`sb3_soup.DecayingNormalActionNoise`
    :param replay_buffer_class: None (as SB3) or an SB3 buffer class, SOUP using its bootstrapped one (:mod:`sb3_soup.buffers`)
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer, as in SB3
    :param n_steps: n-step returns (SB3's ``NStepReplayBuffer``, bootstrapped) when ``replay_buffer_class`` is None
    :param n_heads: number of bootstrapped heads K
    :param n_actor_heads: actor heads (default: ``n_heads``, or the preset's)
    :param n_critic_heads: critic heads (default: ``n_heads``, or the preset's)
    :param preset: one of the paper's models (:data:`sb3_soup.PRESETS`): "ddpg", "ma_bddpg", "multi_ddpg", "dbddpg",
        "soup"; it sets the head counts and the confidence, not the training scheme (for the paper's models, add
        :func:`sb3_soup.paper_settings`, or the paper's update: ``train_heads="active", target_q="own", policy_delay=1,
        target_policy_noise=0.0``)
    :param confidence: the E-Critic's strategy: "none", "fixed", "decayed", "adaptive" (default, or the preset's), "ucb",
        "lcb" or a :class:`sb3_soup.ConfidenceStrategy`
    :param confidence_kwargs: the strategy's arguments by its class's names (None: its defaults), e.g. ``alpha`` of
        :class:`sb3_soup.FixedConfidence`
    :param mask_prob: probability that a head sees a transition, in (0, 1]; 1 turns bootstrap off (default 0.5)
    :param train_heads: "all" (default): every head pair, each with its own masked loss; "active": the episode's head
        pair (the paper); "all_critics": every critic head, the active pair's actor head
    :param target_q: the next state's value each critic head bootstraps from (eq. 4): "min_pair" (default), the smaller
        of its own target head's and one random other's (TD3's clipped double Q across the ensemble); "own", its own
        target head's (the paper);
        "redq", the smaller of two random target heads', the same two for every head (REDQ's target, M = 2)
    :param policy_delay: the actor and the targets are updated once every ``policy_delay`` critic updates (TD3's; the
        paper: 1)
    :param target_policy_noise: std of the noise added to the target actions (TD3's target policy smoothing; the
        paper: 0, none)
    :param target_noise_clip: limit of the absolute value of that noise
    :param check_finite: raise a clear error as soon as an observation, reward, loss or Q value is NaN or inf
    :param stats_window_size: Window size for the rollout logging, in episodes
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation (``net_arch`` in SOUP's or SB3's
        forms, ``activation_fn``...; see :class:`SOUPPolicy`)
    :param verbose: Verbosity level: 0 for no output, 1 for info messages, 2 for debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run ("auto": the GPU if possible)
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
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
        learning_rate: float | Schedule = 1e-3,
        critic_learning_rate: float | Schedule | None = None,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        n_heads: int = 5,
        n_actor_heads: int | None = None,
        n_critic_heads: int | None = None,
        preset: str | None = None,
        confidence: str | ConfidenceStrategy | None = None,
        confidence_kwargs: dict[str, Any] | None = None,
        mask_prob: float | None = None,
        train_heads: str = "all",
        target_q: str = "min_pair",
        policy_delay: int = 2,
        target_policy_noise: float = 0.2,
        target_noise_clip: float = 0.5,
        check_finite: bool = True,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        model = resolve_model(n_heads, n_actor_heads, n_critic_heads, preset, confidence, mask_prob)
        args = check_arguments(**{name: value for name, value in locals().items() if name in ARGUMENT_RULES})
        super().__init__(
            policy,
            env,
            learning_rate,
            args["buffer_size"],
            learning_starts,
            batch_size,
            tau,
            gamma,
            train_freq,
            gradient_steps,
            action_noise=args["action_noise"],  # None: SOUP's default, built by _setup_model
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=dict(replay_buffer_kwargs or {}),  # a copy: the masks' arguments are added to it
            optimize_memory_usage=optimize_memory_usage,
            n_steps=args["n_steps"],
            policy_kwargs=dict(policy_kwargs or {}),
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=args["seed"],
            sde_support=False,
            supported_action_spaces=(spaces.Box,),
            support_multi_env=True,
        )
        self.critic_learning_rate = args["critic_learning_rate"]
        self.n_heads: int = model["n_heads"]
        self.preset: str | None = model["preset"]  # the key of sb3_soup.PRESETS (or None)
        self.n_actor_heads: int = model["n_actor_heads"]
        self.n_critic_heads: int = model["n_critic_heads"]
        self.confidence = model["confidence"]
        self.confidence_kwargs = confidence_kwargs  # the strategy's own arguments, checked by the strategy
        self.mask_prob: float = model["mask_prob"]
        self.train_heads: str = args["train_heads"]
        self.target_q: str = args["target_q"]
        self.policy_delay: int = args["policy_delay"]
        self.target_policy_noise: float = args["target_policy_noise"]
        self.target_noise_clip: float = args["target_noise_clip"]
        self.check_finite: bool = args["check_finite"]
        self._sb3_soup_format = SAVE_FORMAT_VERSION  # saved with the model, checked by SOUP.load
        self._sb3_soup_version = __version__  # the sb3-soup that wrote it

        # Per env: the head pair trained during its current episode (Algorithm 1, drawn at each episode start)
        self._active_pairs: np.ndarray | None = None
        # The selection made at the step being taken, until its rewards come back (for the confidence strategy)
        self._last_selection: tuple[PyTorchObs, Selection] | None = None
        # Saved with the model, so that a resumed run logs what the uninterrupted one would have
        self._stats = EnsembleStats(self.n_actor_heads, self.n_critic_heads)

        if _init_setup_model:
            self._setup_model()

    def _get_policy_from_name(self, policy_name: str) -> type[BasePolicy]:
        if policy_name not in self.policy_aliases:
            aliases = sorted(self.policy_aliases)
            raise ValueError(f"policy must be one of {aliases} or a sb3_soup.SOUPPolicy subclass, got {policy_name!r}")
        return self.policy_aliases[policy_name]

    def _policy_arguments(self) -> dict[str, Any]:
        """SOUP's own arguments of its policy (head counts, confidence strategy), passed besides ``policy_kwargs``."""
        return {name: getattr(self, name) for name in SET_BY_SOUP}

    def _setup_model(self) -> None:
        user_kwargs = self.policy_kwargs
        policy_kwargs = {**user_kwargs, **self._policy_arguments()}
        check_policy(self.policy_class, policy_kwargs, self.observation_space, sorted(self.policy_aliases))
        self.replay_buffer_class = bootstrapped_buffer_class(
            self.replay_buffer_class, self.observation_space, self.n_steps, self.gamma, self.replay_buffer_kwargs
        )
        self.replay_buffer_kwargs.update(n_masks=max(self.n_actor_heads, self.n_critic_heads), mask_prob=self.mask_prob)
        if issubclass(self.replay_buffer_class, HerReplayBuffer) and self.env is None:
            raise ValueError(
                "a model with a HerReplayBuffer needs its env (it computes the rewards of the relabelled goals): "
                "load it with SOUP.load(path, env=...)"
            )
        # SB3 builds the policy from self.policy_kwargs, which stays what the user passed (SB3's load compares it)
        self.policy_kwargs = policy_kwargs
        try:
            with warnings.catch_warnings():
                # SB3 warns n_steps is ignored whenever the class is set; bootstrapped_buffer_class warned if it was
                warnings.filterwarnings("ignore", message=r"`n_steps=\d+` is ignored", category=UserWarning)
                super()._setup_model()
        finally:
            self.policy_kwargs = user_kwargs
        self._create_aliases()
        # None: the critic follows learning_rate (self.lr_schedule, read at each training round, as SB3 reads it)
        self.critic_lr_schedule = None if self.critic_learning_rate is None else _as_schedule(self.critic_learning_rate)
        update_learning_rate(self.critic.optimizer, self._critic_lr_schedule()(1))
        if self.action_noise is None:  # SOUP's rule: N(0, 0.1) (a loaded model has the noise it was saved with)
            assert self.action_space.shape is not None
            self.action_noise = default_action_noise(self.action_space.shape)

    def _critic_lr_schedule(self) -> Schedule:
        """The critic's learning rate schedule: ``critic_learning_rate``'s, or ``learning_rate``'s when it is None."""
        return self.lr_schedule if self.critic_lr_schedule is None else self.critic_lr_schedule

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.actor_target = self.policy.actor_target
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target

    # ----- acting (Algorithm 1) ---------------------------------------------------------------------------------

    def _draw_active_pairs(self, envs: np.ndarray) -> None:
        """Algorithm 1: every episode starts with a randomly selected head pair (one per env)."""
        assert self._active_pairs is not None
        self._active_pairs[envs] = np.random.randint(self.policy.n_pairs, size=len(envs))

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """The E-action for every env (eq. 7) plus exploration noise; random actions, without noise, in the warm-up."""
        if self.num_timesteps < learning_starts:
            return super()._sample_action(learning_starts, None, n_envs)
        assert self._last_obs is not None, "self._last_obs was not set"
        obs_tensor, _ = self.policy.obs_to_tensor(self._last_obs)
        with th.no_grad():
            selection = self.policy.select(obs_tensor, explore=True)
        if self.check_finite:
            check_selection(selection, type(self.policy.confidence).__name__, self.num_timesteps)
        self._stats.record(selection)
        self._last_selection = (obs_tensor, selection)
        action_shape = self.action_space.shape
        assert action_shape is not None
        # (n_envs, *action_shape) in [-1, 1], as SB3's predict shapes actions (the buffer stores them flat)
        scaled_action = selection.actions.cpu().numpy().reshape((-1, *action_shape))
        if action_noise is not None:
            scaled_action = np.clip(scaled_action + action_noise(), -1.0, 1.0)
        return self.policy.unscale_action(scaled_action), scaled_action

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
            check_finite_env_output("observation", new_obs, f"by the environment at step {self.num_timesteps}")
            check_finite_env_output("reward", reward, f"by the environment at step {self.num_timesteps}")
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        # eq. 8's data: the strategy is told what happened (the selection, if the ensemble made one, and the rewards)
        observations, selection = self._last_selection or (None, None)
        rewards = th.as_tensor(np.asarray(reward, dtype=np.float32), device=self.device)
        if selection is None or selection.q_matrix is None:  # a random warm-up action, or no critic ensemble to weigh
            self.policy.confidence.observe(ConfidenceStep(None, None, None, rewards))
        else:
            self.policy.confidence.observe(ConfidenceStep(observations, selection.q_matrix, selection.chosen, rewards))
        self._last_selection = None
        self._draw_active_pairs(np.flatnonzero(dones))

    # ----- training -------------------------------------------------------------------------------------------

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        # Switch to train mode (this affects batch norm / dropout)
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer])
        critic_lr = self._critic_lr_schedule()(self._current_progress_remaining)
        update_learning_rate(self.critic.optimizer, critic_lr)

        # Shapes: P head pairs, H of them trained by a loss (one pair gives (B, ...), which broadcasts as (1, B, ...))
        critic_losses, actor_losses = [], []
        for _ in range(gradient_steps):
            self._n_updates += 1
            data: Samples = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr,assignment]
            critic_pairs, actor_pairs = self._training_pairs(data.masks)
            if not critic_pairs:
                continue  # this minibatch holds nothing for the heads to train
            # The heads of the pairs trained: pair k is actor head k with critic head k (a single head serves every pair)
            target_actor_heads, critic_heads = self.policy.actor_heads(critic_pairs), self.policy.critic_heads(critic_pairs)
            # For n-step replay, discount factor is gamma**n_steps (when no early termination)
            discounts = data.discounts if data.discounts is not None else self.gamma

            with th.no_grad():
                # Eq. 4 from pair k's target heads, y = r + gamma * (1 - done) * Q'_k(s', mu'_k(s')) (+ smoothing, min_pair)
                next_actions = self.actor_target(data.next_observations, head=target_actor_heads.head_arg)  # (H or 1, B, A)
                if self.target_policy_noise > 0:  # TD3's target policy smoothing
                    noise = th.randn_like(next_actions) * self.target_policy_noise
                    noise = noise.clamp(-self.target_noise_clip, self.target_noise_clip)
                    next_actions = (next_actions + noise).clamp(-1.0, 1.0)
                next_features = self.critic_target.body_features(data.next_observations, next_actions)  # (H or 1, B, F)
                if self.target_q == "redq" and self.n_critic_heads > 1:  # REDQ's: the min over 2 random heads, for every pair
                    drawn = th.randperm(self.n_critic_heads, device=self.device)[:2]  # (2,)
                    next_q = th.minimum(*[self.critic_target.heads(next_features, j.repeat(len(critic_pairs))) for j in drawn])
                else:
                    next_q = self.critic_target.heads(next_features, critic_heads.head_arg)  # (H, B, 1)
                    if self.target_q == "min_pair" and self.n_critic_heads > 1:  # TD3's clipped double Q across heads
                        own = th.as_tensor(critic_heads.per_pair, device=self.device)  # (H,)
                        others = (own + th.randint_like(own, 1, self.n_critic_heads)) % self.n_critic_heads  # (H,)
                        next_q = th.minimum(next_q, self.critic_target.heads(next_features, others))  # (H, B, 1)
                target_q = data.rewards + (1 - data.dones) * discounts * next_q  # (H, B, 1)

            # Eq. 3, each critic head's squared error over the transitions its bootstrap mask keeps
            current_q = self.critic(data.observations, data.actions, head=critic_heads.head_arg)  # (H, B, 1)
            critic_masks = data.masks[:, critic_pairs].T.unsqueeze(-1).float()  # (H, B, 1), 1.0 where pair h sees transition b
            critic_loss = masked_mean((target_q - current_q) ** 2, critic_masks)  # (H,)
            critic_losses.append(self._optimize(self.critic, critic_loss, critic_heads, critic_pairs, "critic_loss"))

            # Delayed policy updates
            if self._n_updates % self.policy_delay == 0 and actor_pairs:
                # Eq. 5 as a loss (its gradient is the deterministic policy gradient): -Q_k(s, mu_k(s)), masked
                actor_heads, scoring_heads = self.policy.actor_heads(actor_pairs), self.policy.critic_heads(actor_pairs)
                actions_pi = self.actor(data.observations, head=actor_heads.head_arg)  # (H, B, A)
                q_pi = self.critic(data.observations, actions_pi, head=scoring_heads.head_arg)  # (H, B, 1)
                actor_masks = data.masks[:, actor_pairs].T.unsqueeze(-1).float()  # (H, B, 1)
                actor_loss = -masked_mean(q_pi, actor_masks)  # (H,)
                actor_losses.append(self._optimize(self.actor, actor_loss, actor_heads, actor_pairs, "actor_loss"))
                # Eq. 6: Polyak update of the target networks' bodies and of the heads trained
                soft_update(self.actor, self.actor_target, self.tau, actor_heads.rows)
                soft_update(self.critic, self.critic_target, self.tau, critic_heads.rows)

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/critic_learning_rate", critic_lr)
        exploration_std = noise_std(self.action_noise)  # a DecayingNormalActionNoise's (SOUP's default is one)
        if exploration_std is not None:
            self.logger.record("train/noise_std", exploration_std)
        if critic_losses:
            self.logger.record("train/critic_loss", np.mean(critic_losses))
        if actor_losses:
            self.logger.record("train/actor_loss", np.mean(actor_losses))
        # Eq. 8: the confidence strategy learns from what it observed since the last round
        strategy = self.policy.confidence
        logs = check_update_logs(strategy, strategy.update())
        if self.check_finite and "confidence_loss" in logs:
            name = type(strategy).__name__
            check_loss("confidence_loss", logs["confidence_loss"], lambda: f"the {name}", self._n_updates, self.num_timesteps)
        for key, value in logs.items():
            self.logger.record(f"train/{key}", value)

    def _training_pairs(self, masks: th.Tensor) -> tuple[list[int], list[int]]:
        """
        The head pairs this minibatch trains (``train_heads``), as (critic pairs, actor pairs); with n_envs > 1, "active"
        takes the envs' pairs in turn (one per gradient step). A pair whose mask keeps none of the minibatch is left out.

        :param masks: ``(B, P)`` bootstrap masks of the minibatch
        """
        assert self._active_pairs is not None
        active = [int(self._active_pairs[(self._n_updates - 1) % len(self._active_pairs)])]
        every = list(range(self.policy.n_pairs))
        critic_pairs = active if self.train_heads == "active" else every
        actor_pairs = every if self.train_heads == "all" else active
        has_data = masks.any(dim=0)  # (P,)
        if bool(has_data.all()):
            return critic_pairs, actor_pairs
        kept = has_data.tolist()
        return [pair for pair in critic_pairs if kept[pair]], [pair for pair in actor_pairs if kept[pair]]

    def _optimize(
        self, model: EnsembleActor | EnsembleCritic, per_pair: th.Tensor, heads: TrainedHeads, pairs: list[int], name: str
    ) -> float:
        """
        One gradient step on ``model`` alone (the actor loss leaves no gradient in the critic) for the sum of the pairs'
        losses, as TD3 sums its critics' losses: each head gets the gradient of its own loss (of the sum of its pairs'
        when one head serves them all), the shared body the sum over its heads. The heads left out keep their values and
        their Adam state (see EnsembleAdam).

        :return: the mean loss of the pairs, checked to be finite (``check_finite``)
        """
        loss = per_pair.sum()
        model.optimizer.zero_grad()
        loss.backward(inputs=model.all_parameters())
        if isinstance(model.optimizer, EnsembleAdam):
            model.optimizer.step(head=heads.rows)
        else:
            model.optimizer.step()
        value = per_pair.mean().item()
        if self.check_finite:
            check_loss(name, value, lambda: self.policy.describe_pairs(pairs, per_pair), self._n_updates, self.num_timesteps)
        return value

    # ----- logging, learning ------------------------------------------------------------------------------------

    def dump_logs(self) -> None:
        """Log the ensemble statistics since the last dump, then SB3's usual rollout logs."""
        self._stats.dump(self.logger)
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
        if self.check_finite and self._last_obs is not None:
            check_finite_env_output("observation", self._last_obs, "by env.reset()")
        if resets_env or self._active_pairs is None or len(self._active_pairs) != self.n_envs:
            self._active_pairs = np.zeros(self.n_envs, dtype=np.int64)
            self._draw_active_pairs(np.arange(self.n_envs))  # new episodes
            self._last_selection = None
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

    # ----- saving: SB3's two hooks (loading: sb3_soup.loading.CheckedLoading, with SOUP's checks) ---------------

    def _excluded_save_params(self) -> list[str]:
        # Exclude aliases, and the selection being taken (None between two steps, where models are saved)
        aliases = ["actor", "actor_target", "critic", "critic_target"]
        return [*super()._excluded_save_params(), *aliases, "_last_selection"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        if self.policy.confidence.optimizer is not None:
            state_dicts.append("policy.confidence.optimizer")
        return state_dicts, []
