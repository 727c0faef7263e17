"""Bad input gets a clear error: each case of docs/reliability.md, with the message the user sees."""

import re
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import TD3
from stable_baselines3.common.torch_layers import NatureCNN
from stable_baselines3.common.vec_env import DummyVecEnv, VecCheckNan

from sb3_soup import SOUP, ConfidenceStrategy

TINY = dict(net_arch=dict(pi_body=[8], pi_head=[8], qf_body=[8, 8], qf_head=[8]))
SMALL = dict(learning_starts=20, batch_size=16, buffer_size=500, policy_kwargs=TINY)


class ToyEnv(gym.Env):
    """20-step episodes of random observations from a given space, with a given action space."""

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space):
        self.observation_space = observation_space
        self.action_space = action_space

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.observation_space.seed(int(self.np_random.integers(2**31)))
        self.t = 0
        return self.observation_space.sample(), {}

    def step(self, action):
        self.t += 1
        return self.observation_space.sample(), 0.0, False, self.t >= 20, {}


BOX = spaces.Box(-1, 1, (3,), np.float32)
ACTIONS = spaces.Box(-1, 1, (1,), np.float32)


# ---------------------------------------------------------------- spaces and policies


@pytest.mark.parametrize(
    "action_space", [spaces.Discrete(3), spaces.MultiDiscrete([2, 3]), spaces.MultiBinary(2)], ids=lambda s: type(s).__name__
)
def test_non_box_action_spaces_are_refused_by_sb3(action_space):
    with pytest.raises(AssertionError, match=r"only supports \(<class 'gymnasium.spaces.box.Box'>,\) as action spaces"):
        SOUP("MlpPolicy", ToyEnv(BOX, action_space))


def test_unbounded_actions_are_refused_by_sb3():
    with pytest.raises(AssertionError, match="Continuous action space must have a finite lower and upper bound"):
        SOUP("MlpPolicy", ToyEnv(BOX, spaces.Box(-np.inf, np.inf, (2,), np.float32)))


def test_policies_that_do_not_fit_are_refused():
    with pytest.raises(ValueError, match=re.escape("policy must be one of ['CnnPolicy', 'MlpPolicy', 'MultiInputPolicy']")):
        SOUP("RecurrentPolicy", "Pendulum-v1")
    with pytest.raises(ValueError, match=r"NatureCNN \(CnnPolicy's features extractor\) takes image observations.*got Box"):
        SOUP("CnnPolicy", "Pendulum-v1")
    with pytest.raises(ValueError, match=r"policy must be 'MlpPolicy' for Box.*'MultiInputPolicy' is for Dict"):
        SOUP("MultiInputPolicy", "Pendulum-v1")
    with pytest.raises(ValueError, match=r"You must use `MultiInputPolicy` when working with dict observation space"):  # SB3's
        SOUP("MlpPolicy", ToyEnv(spaces.Dict({"a": BOX}), ACTIONS))
    with pytest.raises(
        ValueError, match=re.escape("SOUPPolicy subclass, got <class 'stable_baselines3.td3.policies.TD3Policy'>")
    ):
        SOUP(TD3.policy_aliases["MlpPolicy"], "Pendulum-v1")


def test_image_observations_with_mlp_policy_are_flattened_with_a_warning():
    """As SB3's DDPG: MlpPolicy flattens the pixels (scaled to [0, 1]); SOUP says so and how to get a CNN."""
    images = spaces.Box(0, 255, (8, 8, 1), np.uint8)
    with pytest.warns(
        UserWarning, match=r"observations are images \(1, 8, 8\): MlpPolicy flattens.*use policy='CnnPolicy'"
    ) as w:
        model = SOUP("MlpPolicy", ToyEnv(images, ACTIONS), n_heads=2, **SMALL)
    assert w[0].filename == __file__  # at the user's line, however deep SB3 builds the policy
    model.learn(30)  # learns (on flattened pixels)
    assert model.actor.features_extractor.__class__.__name__ == "FlattenExtractor" and model.num_timesteps == 30

    big_images = spaces.Box(0, 255, (36, 36, 1), np.uint8)  # NatureCNN's smallest input
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning when a CNN is asked for
        cnn = SOUP(
            "MlpPolicy",
            ToyEnv(big_images, ACTIONS),
            n_heads=2,
            policy_kwargs=dict(features_extractor_class=NatureCNN, features_extractor_kwargs=dict(features_dim=8), **TINY),
        )
    assert isinstance(cnn.actor.features_extractor, NatureCNN)
    assert cnn.predict(big_images.sample(), deterministic=True)[0].shape == (1,)


# ---------------------------------------------------------------- constructor arguments

# (arguments, parameter named, accepted values quoted in the message)
INVALID = [
    (dict(n_heads=0), "n_heads", "an integer >= 1"),
    (dict(n_heads=2.5), "n_heads", "an integer >= 1"),
    (dict(n_heads="3"), "n_heads", "an integer >= 1"),
    (dict(n_heads=True), "n_heads", "an integer >= 1"),
    (dict(n_actor_heads=0), "n_actor_heads", "an integer >= 1"),
    (dict(n_actor_heads=3, n_critic_heads=2), "n_actor_heads and n_critic_heads", "equal or one of them 1"),
    (dict(mask_prob=0.0), "mask_prob", re.escape("a float in (0, 1]")),
    (dict(mask_prob="0.5"), "mask_prob", re.escape("a float in (0, 1]")),
    (dict(mask_prob=True), "mask_prob", re.escape("a float in (0, 1]")),
    (dict(confidence="fixed", confidence_kwargs=dict(alpha=1.0)), "alpha", re.escape("a float in (0, 1)")),
    (dict(confidence="fixed", confidence_kwargs=dict(alpha="0.5")), "alpha", re.escape("a float in (0, 1)")),
    (dict(confidence="decayed", confidence_kwargs=dict(decay=0.0)), "decay", re.escape("a float in (0, 1]")),
    (dict(confidence="decayed", confidence_kwargs=dict(decay=float("nan"))), "decay", re.escape("a float in (0, 1]")),
    (dict(confidence_kwargs=dict(temperature=0)), "temperature", re.escape("a float in (0, inf)")),
    (dict(confidence_kwargs=dict(lr=-1.0)), "lr", re.escape("a float in (0, inf)")),
    (dict(confidence_kwargs=dict(baseline="yes")), "baseline", "True or False"),
    (
        dict(confidence_kwargs=dict(alpha=0.5)),
        "confidence_kwargs",
        re.escape("for confidence='adaptive': AdaptiveConfidence accepts ['baseline'"),
    ),
    (dict(preset="dbddpg", confidence_kwargs=dict(lr=1e-3)), "confidence_kwargs", re.escape("NoConfidence accepts []")),
    (dict(confidence_kwargs=[0.5]), "confidence_kwargs", re.escape("None or a dict of the strategy's arguments")),
    (dict(check_finite=1), "check_finite", "True or False"),
    (dict(confidence="sometimes"), "confidence", re.escape("one of ('none', 'fixed', 'decayed', 'adaptive', 'ucb', 'lcb')")),
    (dict(confidence="ucb", confidence_kwargs=dict(ucb_lambda=-1.0)), "ucb_lambda", re.escape("a float in [0, inf)")),
    (
        dict(confidence_kwargs=dict(temperature_mode="scaled")),
        "temperature_mode",
        re.escape("one of ('absolute', 'relative')"),
    ),
    (dict(confidence=42), "confidence", "ConfidenceStrategy subclass"),
    (dict(preset="td3"), "preset", re.escape("one of ['dbddpg', 'ddpg', 'ma_bddpg', 'multi_ddpg', 'soup']")),
    (dict(preset=3), "preset", re.escape("one of ['dbddpg', 'ddpg', 'ma_bddpg', 'multi_ddpg', 'soup']")),
    (dict(preset="dbddpg", confidence="adaptive"), "preset='dbddpg'", "sets confidence='none'"),
    (dict(train_heads="some"), "train_heads", re.escape("one of ('active', 'all', 'all_critics')")),
    (dict(train_heads=None), "train_heads", re.escape("one of ('active', 'all', 'all_critics')")),
    (dict(target_q="max"), "target_q", re.escape("one of ('own', 'min_pair', 'redq')")),
    (dict(policy_delay=0), "policy_delay", "integer >= 1"),
    (dict(target_policy_noise=-0.1), "target_policy_noise", re.escape("a float in [0, inf)")),
    (dict(target_noise_clip=float("nan")), "target_noise_clip", re.escape("a float in [0, inf)")),
    (dict(buffer_size=1000.5), "buffer_size", re.escape("an integer (replay buffer size)")),
    (dict(critic_learning_rate=0.0), "critic_learning_rate", "a float > 0 or a schedule"),
    (dict(action_noise=0.1), "action_noise", "None .* or an instance of stable_baselines3.common.noise.ActionNoise"),
    (dict(seed=-1), "seed", re.escape("None or an integer in [0, 2**32 - 1]")),
    (dict(seed="0"), "seed", re.escape("None or an integer in [0, 2**32 - 1]")),
    (dict(replay_buffer_kwargs=dict(mask_prob=0.3)), "replay_buffer_kwargs", "pass mask_prob to SOUP"),
    (dict(replay_buffer_class=dict), "replay_buffer_class", "subclass of sb3_soup.BootstrappedReplayBuffer"),
    (dict(policy_kwargs=dict(net_arch="big")), "net_arch", "a list of layer sizes .* dict with keys .*'pi_body', 'pi_head'"),
    (dict(policy_kwargs=dict(net_arch=[64, 0])), "net_arch", re.escape("a list of positive ints (layer sizes)")),
    (dict(policy_kwargs=dict(net_arch=dict(qf_body=[64]))), "qf_body", re.escape("at least 2 layers")),
    (dict(policy_kwargs=dict(net_arch=dict(qf_body=[64]))), "qf_body", re.escape("net_arch['qf_action_layer']=0")),
    (dict(policy_kwargs=dict(net_arch=dict(qf_action_layer=2))), "qf_action_layer", re.escape("must be 0 (")),
    (dict(policy_kwargs=dict(net_arch=dict(pi=[64]))), "net_arch", re.escape("needs the keys ['pi', 'qf']")),
    (dict(policy_kwargs=dict(net_arch=dict(pi=[64], qf=[64], pi_body=[8]))), "net_arch", re.escape("and no other")),
    (dict(policy_kwargs=dict(net_arch=dict(pi=[64], qf=[-1]))), re.escape("net_arch['qf']"), "a list of positive ints"),
    (dict(policy_kwargs=dict(net_arch=dict(pie=[64]))), "net_arch", "accepted keys: .*'pi_body'.* \\['pi', 'qf'\\]"),
    (dict(policy_kwargs=dict(n_critics=0)), "n_critics", "an integer >= 1"),
    (dict(critic_learning_rate="1e-3"), "critic_learning_rate", re.escape("(or None: the same as learning_rate)")),
    (dict(policy_kwargs=dict(net_arch=dict(pi_body=64))), re.escape("net_arch['pi_body']"), "a list of positive ints"),
    (dict(policy_kwargs=dict(net_arch=dict(pi_head=[0]))), re.escape("net_arch['pi_head']"), "a list of positive ints"),
    (dict(policy_kwargs=dict(activation_fn=th.nn.ReLU())), "activation_fn", re.escape("an nn.Module class")),
    (dict(policy_kwargs=dict(n_critic_heads=3)), "policy_kwargs", re.escape("set them as SOUP arguments")),
    (dict(policy_kwargs=dict(nett_arch={})), "policy_kwargs", re.escape("SOUPPolicy accepts ['activation_fn'")),
    (
        dict(policy_kwargs=dict(optimizer_kwargs=dict(capturable=True))),
        "capturable",
        "False only.*optimizer_class=torch.optim.Adam",
    ),
    (dict(policy_kwargs=dict(optimizer_kwargs=dict(differentiable=True))), "differentiable", "False only"),
    (dict(policy_kwargs=dict(optimizer_kwargs=dict(fused=True, foreach=True))), "fused and foreach", "cannot both be True"),
]


@pytest.mark.parametrize("kwargs, parameter, accepted", INVALID, ids=[str(case[0])[:48] for case in INVALID])
def test_every_invalid_argument_names_the_parameter_and_the_accepted_values(kwargs, parameter, accepted):
    with pytest.raises(ValueError) as error:
        SOUP("MlpPolicy", "Pendulum-v1", **{"buffer_size": 100, **kwargs})
    message = str(error.value)
    assert re.search(parameter, message) and re.search(accepted, message), message
    given = next(iter(kwargs.values()))
    if "confidence_kwargs" in kwargs:  # a strategy's argument
        given = kwargs["confidence_kwargs"]
        given = next(iter(given.values())) if isinstance(given, dict) else given
    if not isinstance(given, (dict, tuple)) and "unknown keys" not in message:  # and what was given
        assert repr(given) in message or str(given) in message, message


# SB3's own arguments are SB3's to check: what SB3's TD3 accepts, SOUP accepts
SB3_ACCEPTS = [
    dict(tau=0.0),
    dict(gamma=1.5),
    dict(batch_size=0),
    dict(learning_starts=-1),
    dict(gradient_steps=-2),
    dict(stats_window_size=0),
    dict(n_steps=0),
]


@pytest.mark.parametrize("kwargs", SB3_ACCEPTS, ids=str)
def test_what_sb3_accepts_of_its_own_arguments_soup_accepts(kwargs):
    TD3("MlpPolicy", "Pendulum-v1", buffer_size=100, **kwargs)
    SOUP("MlpPolicy", "Pendulum-v1", buffer_size=100, **kwargs)


# and what it refuses, SOUP refuses with SB3's error
SB3_REFUSES = [
    (dict(train_freq=(1, "epoch")), ValueError, "The unit of the `train_freq` must be either 'step' or 'episode' not 'epoch'"),
    (dict(learning_rate="1e-3"), AssertionError, "The learning rate schedule must be a float or a callable, not 1e-3"),
]


@pytest.mark.parametrize("kwargs, error, message", SB3_REFUSES, ids=[str(case[0]) for case in SB3_REFUSES])
def test_what_sb3_refuses_of_its_own_arguments_gets_sb3s_error(kwargs, error, message):
    for algo in (TD3, SOUP):
        with pytest.raises(error, match=re.escape(message)):
            algo("MlpPolicy", "Pendulum-v1", buffer_size=100, **kwargs)


def test_numpy_scalars_are_accepted_and_stored_as_python_numbers():
    model = SOUP(
        "MlpPolicy",
        "Pendulum-v1",
        n_heads=np.int64(3),
        mask_prob=np.float64(0.5),
        confidence="fixed",
        confidence_kwargs=dict(alpha=np.float32(0.25)),
        check_finite=np.bool_(True),
        batch_size=np.int32(16),
        buffer_size=np.int64(100),
        policy_kwargs=dict(net_arch=dict(pi_body=[np.int64(8)], pi_head=[8], qf_body=[8, 8], qf_head=[8])),
    )
    assert (model.n_heads, model.n_actor_heads, model.policy.confidence.alpha, model.batch_size) == (3, 3, 0.25, 16)
    assert type(model.n_heads) is int and type(model.policy.confidence.alpha) is float and type(model.check_finite) is bool
    assert model.policy.net_arch["pi_body"] == [8]


def test_integers_given_as_floats_are_taken_as_those_integers():  # YAML's 1.0e+3, a sampler's 2.0; TD3 takes policy_delay=2.0
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3.0, policy_delay=np.float64(2), buffer_size=1.0e3, n_steps=1.0)
    assert (model.n_heads, model.policy_delay, model.buffer_size, model.n_steps) == (3, 2, 1000, 1)
    assert all(type(value) is int for value in (model.n_heads, model.policy_delay, model.buffer_size, model.n_steps))


# ---------------------------------------------------------------- custom confidence strategies


class _Duck:
    def weights(self, obs, q_matrix):
        return th.ones(1, 1, 1)


class _NoSuperInit(ConfidenceStrategy):
    def __init__(self):
        self.scale = 1.0

    def weights(self, obs, q_matrix):
        return th.ones(1, 1, 1)


class _NumpyWeights(ConfidenceStrategy):
    def weights(self, obs, q_matrix):
        return np.ones((1, self.n_critic_heads, self.n_actor_heads))


class _NaNWeights(ConfidenceStrategy):
    def weights(self, obs, q_matrix):
        return th.full((1, self.n_critic_heads, self.n_actor_heads), float("nan"))


class _UpdateReturnsNone(ConfidenceStrategy):
    def weights(self, obs, q_matrix):
        return th.ones(1, 1, 1)

    def update(self):
        self.seen = True  # forgets to return the logs


class _DivergingUpdate(_UpdateReturnsNone):
    def update(self):
        return {"confidence_loss": float("nan")}


def test_custom_strategies_that_do_not_follow_the_interface():
    with pytest.raises(ValueError, match=re.escape("it has a weights method: subclass sb3_soup.ConfidenceStrategy")):
        SOUP("MlpPolicy", "Pendulum-v1", confidence=_Duck())
    with pytest.raises(ValueError, match=re.escape("_NoSuperInit.__init__ must call super().__init__()")):
        SOUP("MlpPolicy", "Pendulum-v1", confidence=_NoSuperInit())

    class NoWeights(ConfidenceStrategy):
        pass

    with pytest.raises(TypeError, match="Can't instantiate abstract class NoWeights"):  # Python's own
        NoWeights()

    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, confidence=_NumpyWeights(), **SMALL)
    with pytest.raises(ValueError, match=re.escape("_NumpyWeights.weights must return a torch.Tensor broadcastable to")):
        model.predict(np.zeros(3, dtype=np.float32))  # first use

    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, confidence=_NaNWeights(), **SMALL)
    with pytest.raises(FloatingPointError, match="the confidence strategy _NaNWeights gave non-finite weights"):
        model.learn(50)
    assert model.num_timesteps == SMALL["learning_starts"]  # at its first selection

    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, confidence=_UpdateReturnsNone(), **SMALL)
    with pytest.raises(ValueError, match=re.escape("_UpdateReturnsNone.update must return a dict of values to log")):
        model.learn(50)

    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, confidence=_DivergingUpdate(), **SMALL)
    with pytest.raises(FloatingPointError, match=r"non-finite confidence_loss \(nan\) for the _DivergingUpdate at update 1"):
        model.learn(50)


# ---------------------------------------------------------------- non-finite data, Q values and losses


class _Corrupt(gym.Wrapper):
    """Puts ``value`` into the observation or the reward at step ``at`` (0: the reset observation)."""

    def __init__(self, env, at: int, value: float, where: str = "observation"):
        super().__init__(env)
        self.at, self.value, self.where, self.t = at, value, where, 0

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return (obs * self.value if self.at == 0 else obs), info

    def step(self, action):
        self.t += 1
        obs, reward, terminated, truncated, info = self.env.step(action)
        if self.t == self.at and self.where == "observation":
            obs = obs.copy()
            obs[1] = self.value
        if self.t == self.at and self.where == "reward":
            reward = self.value
        return obs, reward, terminated, truncated, info


CORRUPTIONS = [(0, np.nan, "observation"), (17, np.inf, "observation"), (23, -np.inf, "reward")]


@pytest.mark.parametrize("at, value, where", CORRUPTIONS)
def test_non_finite_observations_and_rewards_stop_at_the_step_they_appear(at, value, where):
    model = SOUP("MlpPolicy", _Corrupt(gym.make("Pendulum-v1"), at, value, where), n_heads=2, **SMALL)
    place = "env.reset()" if at == 0 else f"the environment at step {at}"
    with pytest.raises(ValueError, match=rf"non-finite {where} \(NaN or inf\) returned by {re.escape(place)}.*VecCheckNan"):
        model.learn(50)
    assert model.num_timesteps == at


def test_check_finite_false_trains_on_and_vec_check_nan_is_the_alternative():
    model = SOUP("MlpPolicy", _Corrupt(gym.make("Pendulum-v1"), 5, np.nan, "reward"), check_finite=False, n_heads=2, **SMALL)
    model.learn(10)  # no check: the NaN reward went into the replay buffer
    assert np.isnan(model.replay_buffer.rewards[:10]).any()
    # SB3's VecCheckNan, documented as the other way to find the culprit, raises at the same step
    env = VecCheckNan(DummyVecEnv([lambda: _Corrupt(gym.make("Pendulum-v1"), 5, np.nan, "reward")]), raise_exception=True)
    model = SOUP("MlpPolicy", env, check_finite=False, n_heads=2, **SMALL)
    with pytest.raises(ValueError, match=r"(?i)found NaN in rewards"):
        model.learn(10)
    assert model.num_timesteps == 4


def _trained(**kwargs) -> SOUP:
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, seed=0, **{**SMALL, **kwargs})
    model.learn(30)
    return model


def _poison(module: th.nn.Module, head: int, value: float = float("nan")) -> None:
    with th.no_grad():
        module.heads.layers[-1].bias[head].fill_(value)


def test_non_finite_q_values_while_acting_name_the_head():
    model = _trained()
    _poison(model.critic, 2, float("inf"))
    with pytest.raises(FloatingPointError, match=r"while acting at step 30: critic head\(s\) \[2\] gave non-finite Q values"):
        model.learn(10, reset_num_timesteps=False)

    model = _trained()
    _poison(model.actor, 0)
    with pytest.raises(FloatingPointError, match=r"candidate\(s\) of actor head\(s\) \[0\].*actor head\(s\) \[0\] proposed"):
        model.learn(10, reset_num_timesteps=False)

    model = _trained(preset="ddpg")  # one head: no Q matrix, the action itself is checked
    _poison(model.actor, 0)
    with pytest.raises(FloatingPointError, match=r"actor head\(s\) \[0\] proposed non-finite actions"):
        model.learn(10, reset_num_timesteps=False)


@pytest.mark.parametrize("train_heads", ["active", "all"])
def test_non_finite_losses_name_the_loss_and_the_head_pair(train_heads):
    model = _trained(train_heads=train_heads, target_q="own")  # each pair's own target: only pair 1 reads head 1's
    _poison(model.critic_target, 1)  # targets only: acting stays finite, the critic loss of pair 1 does not
    model._active_pairs[:] = 1
    which = re.escape("head pair(s) [1] (actor head(s) [1], critic head(s) [1])")
    with pytest.raises(FloatingPointError, match=rf"non-finite critic_loss \(nan\) for {which} at update \d+ \(step 31\)"):
        model.learn(10, reset_num_timesteps=False)
    assert model.num_timesteps == 31  # stopped at the first update that met it
