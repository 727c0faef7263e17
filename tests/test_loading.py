"""Loading: files that are not models, truncated or corrupt ones, other K or presets, other save formats, buffers."""

import copy
import json
import pickle
import random
import re
import warnings
import zipfile

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.utils import set_random_seed

from sb3_soup import SOUP, __version__
from sb3_soup.loading import SAVE_FORMAT_VERSION
from sb3_soup.presets import PAPER_UPDATE

TINY = dict(net_arch=dict(pi_body=[8], pi_head=[8], qf_body=[8, 8], qf_head=[8]))
SMALL = dict(learning_starts=20, batch_size=16, buffer_size=300, policy_kwargs=TINY)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A SOUP model trained a little, saved with its replay buffer."""
    folder = tmp_path_factory.mktemp("saved")
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, seed=0, **SMALL)
    model.learn(40)
    model.save(folder / "model.zip")
    model.save_replay_buffer(folder / "buffer.pkl")
    return folder


def _rewrite(source, target, change=None, drop=(), truncate=None):
    """Copy a model zip, changing its ``data`` JSON, dropping entries, or truncating the file."""
    if truncate is not None:
        target.write_bytes(source.read_bytes()[:truncate])
        return target
    with zipfile.ZipFile(source) as old, zipfile.ZipFile(target, "w") as new:
        for name in old.namelist():
            if name in drop:
                continue
            content = old.read(name)
            if name == "data" and change is not None:
                data = json.loads(content)
                change(data)
                content = json.dumps(data).encode()
            new.writestr(name, content)
    return target


# ---------------------------------------------------------------- files that are not (complete) models


def test_files_that_are_not_models(saved, tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(ValueError, match=re.escape(f"{text} is not a saved model: it is not a zip archive")):
        SOUP.load(text)
    with pytest.raises(ValueError, match=r"is not a saved model: it is not a zip archive .*load_replay_buffer"):
        SOUP.load(saved / "buffer.pkl")
    no_data = _rewrite(saved / "model.zip", tmp_path / "no_data.zip", drop=("data",))
    with pytest.raises(ValueError, match=re.escape(f"{no_data} is a zip archive but not a saved model: it has no 'data'")):
        SOUP.load(no_data)
    with pytest.raises(FileNotFoundError):
        SOUP.load(tmp_path / "missing.zip")

    td3 = TD3("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8]), buffer_size=100)
    td3.save(tmp_path / "td3.zip")
    with pytest.raises(ValueError, match=r"was not saved by SOUP \(its policy class comes from stable_baselines3\.td3"):
        SOUP.load(tmp_path / "td3.zip")


def test_truncated_and_corrupt_zips(saved, tmp_path):
    size = (saved / "model.zip").stat().st_size
    for cut in (size // 2, size - 10):
        truncated = _rewrite(saved / "model.zip", tmp_path / f"cut_{cut}.zip", truncate=cut)
        with pytest.raises(ValueError, match=r"is a truncated or corrupt model zip .* load an earlier checkpoint"):
            SOUP.load(truncated)
    # a flipped byte inside a parameter file: the zip's CRC check catches it
    corrupt = tmp_path / "corrupt.zip"
    content = bytearray((saved / "model.zip").read_bytes())
    with zipfile.ZipFile(saved / "model.zip") as archive:
        info = archive.getinfo("policy.pth")
    offset = info.header_offset + 30 + len(info.filename) + len(info.extra) + info.compress_size // 2
    content[offset] ^= 0xFF
    corrupt.write_bytes(bytes(content))
    with pytest.raises(ValueError, match=r"corrupt\.zip is a corrupt model zip .*Bad CRC-32"):
        SOUP.load(corrupt)


# ---------------------------------------------------------------- versions


def test_the_version_and_save_format_are_stored_and_no_random_generators(saved):
    with zipfile.ZipFile(saved / "model.zip") as archive:
        data = json.loads(archive.read("data"))
    assert data["_sb3_soup_format"] == SAVE_FORMAT_VERSION and data["_sb3_soup_version"] == __version__
    assert "_rng_state" not in data  # a checkpoint's training state holds them (sb3_soup.checkpoint)


def test_newer_save_formats_are_refused(saved, tmp_path):
    def newer(data):
        data.update(_sb3_soup_format=SAVE_FORMAT_VERSION + 1, _sb3_soup_version="9.0.0")

    future = _rewrite(saved / "model.zip", tmp_path / "future.zip", newer)
    message = (
        f"future.zip was saved by sb3-soup 9.0.0 in save format {SAVE_FORMAT_VERSION + 1}; this sb3-soup {__version__} "
        f"reads save format {SAVE_FORMAT_VERSION} only: upgrade sb3-soup (pip install -U sb3-soup) to load it"
    )
    with pytest.raises(ValueError, match=re.escape(message)):
        SOUP.load(future)


@pytest.mark.parametrize("saved_format", [0, 1])
def test_older_save_formats_are_refused(saved, tmp_path, saved_format):
    """0.1.0a0's files: format 0 (before the format was stored) and format 1 (other attribute names) are not read."""

    def older(data):
        del data["_sb3_soup_format"], data["_sb3_soup_version"]  # format 0: not stored
        if saved_format == 1:
            data.update(_sb3_soup_format=1, _sb3_soup_version="0.1.0a0")

    old = _rewrite(saved / "model.zip", tmp_path / "old.zip", older)
    message = (
        f"old.zip was saved by sb3-soup 0.1.0a0 in save format {saved_format}; this sb3-soup {__version__} reads save "
        f"format {SAVE_FORMAT_VERSION} only: load it with sb3-soup 0.1.0a0 (pip install sb3-soup==0.1.0a0), or train a "
        "new model"
    )
    with pytest.raises(ValueError, match=re.escape(message)):
        SOUP.load(old)


def test_a_development_save_format_of_this_version_is_refused(saved, tmp_path):
    """0.2.0a0's files from before its save format 3 (SOUP's policy arguments in policy_kwargs, a bool baseline flag)."""

    def development(data):
        data.update(_sb3_soup_format=SAVE_FORMAT_VERSION - 1, _sb3_soup_version=__version__)

    old = _rewrite(saved / "model.zip", tmp_path / "old.zip", development)
    message = (
        f"old.zip was saved by sb3-soup {__version__} in save format {SAVE_FORMAT_VERSION - 1}; this sb3-soup "
        f"{__version__} reads save format {SAVE_FORMAT_VERSION} only: it was saved during this version's development, "
        "before its format changed: train a new model"
    )
    with pytest.raises(ValueError, match=re.escape(message)):
        SOUP.load(old)


# ---------------------------------------------------------------- another K, another preset: loaded as saved


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(preset="ma_bddpg", n_heads=3, mask_prob=0.7),
        dict(preset="dbddpg", n_heads=4, **PAPER_UPDATE),
        dict(n_heads=2, confidence="fixed", confidence_kwargs=dict(alpha=0.8)),
    ],
    ids=["ma_bddpg-3", "dbddpg-4-paper-scheme", "fixed-2"],
)
def test_other_head_counts_and_presets_load_as_saved(tmp_path, kwargs):
    model = SOUP("MlpPolicy", "Pendulum-v1", seed=1, **SMALL, **kwargs)
    model.learn(30)
    model.save(tmp_path / "model")
    loaded = SOUP.load(tmp_path / "model", env=make_vec_env("Pendulum-v1"))  # the class defaults are 5 heads, adaptive
    for name in (
        "n_heads",
        "n_actor_heads",
        "n_critic_heads",
        "preset",
        "confidence",
        "confidence_kwargs",
        "mask_prob",
        "train_heads",
        "target_q",
        "policy_delay",
        "target_policy_noise",
    ):
        assert getattr(loaded, name) == getattr(model, name), name
    assert type(loaded.policy.confidence) is type(model.policy.confidence)
    assert loaded.replay_buffer.n_masks == model.replay_buffer.n_masks
    obs = np.random.default_rng(0).normal(size=(8, 3)).astype(np.float32)
    assert np.array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    loaded.learn(20, reset_num_timesteps=False)


def test_load_refuses_to_change_the_structure_and_checks_other_settings(saved):
    with pytest.raises(ValueError, match=r"\['confidence', 'n_heads'\] cannot be changed when loading: .*n_heads=3"):
        SOUP.load(saved / "model.zip", n_heads=5, confidence="none")
    with pytest.raises(ValueError, match=r"\['confidence_kwargs'\] cannot be changed when loading: the saved model was built "
                       r"with confidence_kwargs=None; create a new SOUP"):  # fmt: skip
        SOUP.load(saved / "model.zip", confidence_kwargs=dict(lr=1e-3))
    with pytest.raises(ValueError, match=re.escape("train_heads must be one of ('active', 'all', 'all_critics')")):
        SOUP.load(saved / "model.zip", train_heads="every")
    loaded = SOUP.load(saved / "model.zip", learning_starts=np.int64(5), train_heads="active")
    assert loaded.learning_starts == 5 and loaded.train_heads == "active"  # learning_starts is SB3's: taken as SB3 takes it


def test_load_seeds_the_random_generators_as_sb3_does(saved):
    """The model zip holds no random-generator state: SOUP.load, as SB3's, seeds the generators with the model's seed."""
    np.random.seed(123)  # whatever happened before
    random.seed(123)
    model = SOUP.load(saved / "model.zip")
    after_load = (np.random.random(3), random.random(), model.action_space.sample())
    space = copy.deepcopy(model.action_space)
    set_random_seed(model.seed)
    space.seed(model.seed)
    assert model.seed == 0 and np.array_equal(np.random.random(3), after_load[0]) and random.random() == after_load[1]
    assert np.array_equal(space.sample(), after_load[2])


# ---------------------------------------------------------------- replay buffers


def test_replay_buffers_that_do_not_fit_are_refused(saved, tmp_path):
    model = SOUP.load(saved / "model.zip", env=gym.make("Pendulum-v1"))
    original = model.replay_buffer
    data = (saved / "buffer.pkl").read_bytes()
    (tmp_path / "cut.pkl").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"could not read the replay buffer .*cut\.pkl: the file is truncated or corrupt"):
        model.load_replay_buffer(tmp_path / "cut.pkl")
    assert model.replay_buffer is original  # untouched

    other_k = SOUP("MlpPolicy", "Pendulum-v1", n_heads=4, **SMALL)
    other_k.save_replay_buffer(tmp_path / "k4.pkl")
    with pytest.raises(ValueError, match=r"has bootstrap masks for 4 head pairs, this model has 3"):
        model.load_replay_buffer(tmp_path / "k4.pkl")

    two_envs = SOUP("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2), n_heads=3, **SMALL)
    two_envs.save_replay_buffer(tmp_path / "envs2.pkl")
    with pytest.raises(ValueError, match=r"was filled by 2 envs, this model has 1"):
        model.load_replay_buffer(tmp_path / "envs2.pkl")

    with open(tmp_path / "dict.pkl", "wb") as file:
        pickle.dump({"not": "a buffer"}, file)
    with pytest.raises(ValueError, match=r"holds a dict, not one of sb3_soup's bootstrapped replay buffers"):
        model.load_replay_buffer(tmp_path / "dict.pkl")

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.load_replay_buffer(saved / "buffer.pkl")
    assert model.replay_buffer.size() == 40 and model.replay_buffer.masks.shape == (300, 1, 3)


def test_custom_objects_with_other_networks_get_the_clear_error_not_sb3s_key_error(saved):
    """SB3's load takes a ValueError from set_parameters for its patch of old DQN files (KeyError 'policy.optimizer')."""
    other = dict(net_arch=dict(pi_body=[8], pi_head=[8], qf_body=[8, 8], qf_head=[8], qf_action_layer=0))
    with pytest.raises(RuntimeError, match=r"do not fit this model's networks .*critic.* unless custom_objects gives"):
        SOUP.load(saved / "model.zip", custom_objects={"policy_kwargs": other})
    # as TD3's load: a RuntimeError, naming the mismatch
    td3 = TD3("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8]))
    td3.save(saved / "td3.zip")
    with pytest.raises(RuntimeError, match=r"size mismatch"):
        TD3.load(saved / "td3.zip", custom_objects={"policy_kwargs": dict(net_arch=[16])})
    same = dict(TINY["net_arch"], qf_action_layer=1)  # the same networks, said otherwise: loads
    assert SOUP.load(saved / "model.zip", custom_objects={"policy_kwargs": dict(net_arch=same)}).n_heads == 3


def test_set_parameters_from_a_model_with_other_heads_says_to_use_load(saved):
    five_heads = SOUP("MlpPolicy", "Pendulum-v1", n_heads=5, **SMALL)
    # a RuntimeError, as TD3's set_parameters raises (torch's load_state_dict)
    with pytest.raises(RuntimeError, match=r"do not fit this model's networks .*torch.Size\(\[3, 8, 8\]\).* SOUP.load builds"):
        five_heads.set_parameters(str(saved / "model.zip"))
    three_heads = SOUP("MlpPolicy", "Pendulum-v1", n_heads=3, **SMALL)
    three_heads.set_parameters(str(saved / "model.zip"))  # same shapes: loads
    saved_weight = SOUP.load(saved / "model.zip").actor.heads.layers[0].weight
    assert th.equal(three_heads.actor.heads.layers[0].weight, saved_weight)
