"""CnnPolicy and image keys in MultiInputPolicy, as in SB3: NatureCNN, images scaled to [0, 1], shared or separate
features extractors; learning, save/load and the RL Zoo on a tiny image environment (tests/image_env.py)."""

import os
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from image_env import TinyImageEnv
from stable_baselines3.common.torch_layers import CombinedExtractor, NatureCNN
from stable_baselines3.common.vec_env import VecTransposeImage

import _sb3_soup_zoo_hook
from sb3_soup import SOUP, CnnPolicy

TINY = dict(
    net_arch=dict(pi_body=[8], pi_head=[8], qf_body=[8, 8], qf_head=[8]), features_extractor_kwargs=dict(features_dim=8)
)
SMALL = dict(n_heads=2, learning_starts=20, batch_size=8, buffer_size=200, seed=0, device="cpu")


def cnn_model(share: bool = False, env: gym.Env | None = None, **kwargs) -> SOUP:
    policy_kwargs = dict(TINY, share_features_extractor=share)
    return SOUP("CnnPolicy", env or TinyImageEnv(), policy_kwargs=policy_kwargs, **{**SMALL, **kwargs})


def extractors(model: SOUP) -> list:
    policy = model.policy
    return [
        policy.actor.features_extractor,
        policy.actor_target.features_extractor,
        policy.critic.features_extractor,
        policy.critic_target.features_extractor,
        policy.confidence.network.features_extractor,
    ]


def test_cnn_policy_is_natures_cnn_with_an_extractor_per_network():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "pixels into an MLP" warning
        model = cnn_model()
    assert isinstance(model.policy, CnnPolicy)
    found = extractors(model)
    assert all(isinstance(extractor, NatureCNN) for extractor in found)
    assert len({id(extractor) for extractor in found}) == 5
    # channel-last images are transposed by SB3, as for its own CnnPolicy
    assert isinstance(model.get_env(), VecTransposeImage) and model.observation_space.shape == (3, 36, 36)
    # each network trains its own extractor
    assert {id(p) for p in model.critic.features_extractor.parameters()} <= {id(p) for p in model.critic.all_parameters()}
    confidence_trained = {id(p) for p in model.policy.confidence.optimizer.param_groups[0]["params"]}
    assert {id(p) for p in model.policy.confidence.network.features_extractor.parameters()} <= confidence_trained


def test_images_are_scaled_to_unit_range_as_in_sb3():
    model = cnn_model()
    image = model.observation_space.sample()[None]  # (1, 3, 36, 36) uint8
    obs, _ = model.policy.obs_to_tensor(image)
    extractor = model.actor.features_extractor
    expected = extractor(th.as_tensor(image).float() / 255.0)
    assert th.allclose(model.actor.extract_features(obs, extractor), expected)
    assert not th.allclose(extractor(th.as_tensor(image).float()), expected)


def test_shared_features_extractor_is_the_actors_trained_by_the_actor_only():
    model = cnn_model(share=True)
    policy = model.policy
    actor_extractor, target_extractor, critic_extractor, critic_target_extractor, confidence_extractor = extractors(model)
    assert critic_extractor is actor_extractor and confidence_extractor is actor_extractor
    assert critic_target_extractor is target_extractor and target_extractor is not actor_extractor
    shared = {id(p) for p in actor_extractor.parameters()}
    assert shared <= {id(p) for p in model.actor.all_parameters()}  # the actor's optimizer steps it
    assert not shared & {id(p) for p in model.critic.all_parameters()}  # neither the critic's
    assert not shared & {id(p) for group in policy.confidence.optimizer.param_groups for p in group["params"]}
    # the critic's loss leaves no gradient in it
    obs = th.as_tensor(model.observation_space.sample()[None])
    model.critic(obs, th.zeros(1, 2)).sum().backward()
    assert all(p.grad is None for p in actor_extractor.parameters())
    assert all(p.grad is not None for p in model.critic.joint_layer.parameters())  # the critic's first layer


@pytest.mark.parametrize("share", [False, True], ids=["separate", "shared"])
def test_cnn_policy_learns_saves_and_loads(tmp_path, share):
    model = cnn_model(share=share)
    before = [p.detach().clone() for p in model.actor.features_extractor.parameters()]
    model.learn(40)
    assert model.num_timesteps == 40
    after = list(model.actor.features_extractor.parameters())
    assert any(not th.equal(a, b) for a, b in zip(before, after))  # the CNN learns
    if share:  # and the critic target follows the actor target's (the same module)
        assert model.critic_target.features_extractor is model.actor_target.features_extractor
    images = np.stack([TinyImageEnv().observation_space.sample() for _ in range(4)])  # (4, 36, 36, 3): channel-last
    actions, _ = model.predict(images, deterministic=True)
    assert actions.shape == (4, 2)
    model.save(tmp_path / "model.zip")
    loaded = SOUP.load(tmp_path / "model.zip", device="cpu")
    assert loaded.policy.share_features_extractor is share
    assert (loaded.critic.features_extractor is loaded.actor.features_extractor) is share
    np.testing.assert_array_equal(loaded.predict(images, deterministic=True)[0], actions)
    view = loaded.policy.ensemble_view(images)  # channel-last images, as predict takes them
    np.testing.assert_array_equal(view.actions, actions)
    assert view.q_matrix.shape == (4, 2, 2)
    loaded.set_env(TinyImageEnv())
    loaded.learn(10, reset_num_timesteps=False)  # and trains on
    assert loaded.num_timesteps == 50


def test_channel_first_images_and_every_preset():
    for preset in ("ddpg", "ma_bddpg", "multi_ddpg", "dbddpg", "soup"):
        model = cnn_model(env=TinyImageEnv(channel_first=True), preset=preset)
        assert not isinstance(model.get_env(), VecTransposeImage)
        actions, _ = model.predict(model.observation_space.sample(), deterministic=True)
        assert actions.shape == (2,) and model.action_space.contains(actions)


class DictImageEnv(gym.Env):
    """TinyImageEnv's images with a vector beside them, in a Dict observation."""

    def __init__(self):
        self.images = TinyImageEnv()
        self.observation_space = spaces.Dict({"image": self.images.observation_space, "vector": spaces.Box(-1, 1, (3,))})
        self.action_space = self.images.action_space

    def _wrap(self, image):
        return {"image": image, "vector": self.np_random.uniform(-1, 1, 3).astype(np.float32)}

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        image, info = self.images.reset(seed=seed)
        return self._wrap(image), info

    def step(self, action):
        image, *rest = self.images.step(action)
        return (self._wrap(image), *rest)


@pytest.mark.parametrize("share", [False, True], ids=["separate", "shared"])
def test_image_keys_in_multi_input_policy_get_a_cnn(share):
    policy_kwargs = dict(
        net_arch=TINY["net_arch"], features_extractor_kwargs=dict(cnn_output_dim=8), share_features_extractor=share
    )
    model = SOUP("MultiInputPolicy", DictImageEnv(), policy_kwargs=policy_kwargs, **SMALL)
    extractor = model.actor.features_extractor
    assert isinstance(extractor, CombinedExtractor) and isinstance(extractor.extractors["image"], NatureCNN)
    assert (model.critic.features_extractor is extractor) is share
    model.learn(30)
    actions, _ = model.predict(model.observation_space.sample(), deterministic=True)
    assert actions.shape == (2,)


def test_cnn_policy_refuses_observations_that_are_not_images():
    with pytest.raises(ValueError, match=r"NatureCNN \(CnnPolicy's features extractor\) takes image observations.*MlpPolicy"):
        SOUP("CnnPolicy", "Pendulum-v1")


# ---------------------------------------------------------------- the RL Zoo

HERE = Path(__file__).resolve().parent
ZOO_CONFIG = """
SOUPTinyImage-v0:
  policy: 'CnnPolicy'
  n_timesteps: 60
  n_heads: 2
  learning_starts: 20
  batch_size: 8
  buffer_size: 500
  policy_kwargs: "dict(net_arch=dict(pi_body=[8], pi_head=[8], qf_body=[8, 8], qf_head=[8]),
    features_extractor_kwargs=dict(features_dim=8), share_features_extractor=True)"
"""


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_zoo_trains_cnn_policy_on_an_image_env(tmp_path):
    """`python -m rl_zoo3.train --algo soup --env SOUPTinyImage-v0 --gym-packages image_env` with a CnnPolicy config."""
    config = tmp_path / "soup_images.yml"
    config.write_text(ZOO_CONFIG)
    env = dict(os.environ, MPLBACKEND="Agg", OMP_NUM_THREADS="1", PYTHONPATH=os.pathsep.join([str(HERE), *sys.path]))
    env.pop(_sb3_soup_zoo_hook.ENV_VAR, None)
    args = ["-m", "rl_zoo3.train", "--algo", "soup", "--env", "SOUPTinyImage-v0", "--gym-packages", "image_env"]
    args += ["--conf-file", str(config), "--eval-freq", "-1", "--seed", "0", "-f", str(tmp_path / "logs")]
    result = subprocess.run([sys.executable, *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=500)
    assert result.returncode == 0, f"stdout:\n{result.stdout[-3000:]}\nstderr:\n{result.stderr[-3000:]}"
    saved = tmp_path / "logs" / "soup" / "SOUPTinyImage-v0_1" / "SOUPTinyImage-v0.zip"
    model = SOUP.load(saved, device="cpu")
    assert isinstance(model.policy, CnnPolicy) and model.num_timesteps == 60
    assert model.critic.features_extractor is model.actor.features_extractor
    actions, _ = model.predict(TinyImageEnv().observation_space.sample(), deterministic=True)
    assert actions.shape == (2,)
