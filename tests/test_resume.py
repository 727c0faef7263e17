"""Nothing lost: a run killed with SIGKILL resumes from its last checkpoint, and the resumed run is the uninterrupted one."""

import copy
import dataclasses
import os
import pickle
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from resume_run import KWARGS, SAVE_FREQ, TINY, make_model
from stable_baselines3 import TD3
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_soup import SOUP
from sb3_soup.checkpoint import (
    TRAINING_STATE_FORMAT,
    EnvStateError,
    ResumableCheckpointCallback,
    find_checkpoints,
    get_env_state,
    latest_checkpoint,
    load_checkpoint,
    read_training_state,
    save_checkpoint,
    save_training_state,
    set_env_state,
)
from sb3_soup.presets import PAPER_UPDATE

SCRIPT = Path(__file__).with_name("resume_run.py")


class Recorder(BaseCallback):
    """Records the actions sent to the env, and a snapshot of the model's state between rollouts at step ``at``."""

    def __init__(self, at: int | None = None):
        super().__init__()
        self.actions: list[np.ndarray] = []
        self.at = at
        self.snapshot: dict | None = None

    def _on_step(self) -> bool:
        self.actions.append(self.locals["actions"].copy())
        return True

    def _on_rollout_start(self) -> None:
        if self.model.num_timesteps == self.at:
            self.snapshot = _state(self.model)


def _state(model: SOUP) -> dict:
    """Everything a resumed run must get back (copied)."""
    buffer = model.replay_buffer
    optimizers = {"actor": model.actor.optimizer, "critic": model.critic.optimizer}
    if model.policy.confidence.optimizer is not None:
        optimizers["confidence"] = model.policy.confidence.optimizer
    return copy.deepcopy(
        {
            "num_timesteps": model.num_timesteps,
            "n_updates": model._n_updates,
            "episode_num": model._episode_num,
            "policy": model.policy.state_dict(),
            "optimizers": {name: optimizer.state_dict()["state"] for name, optimizer in optimizers.items()},
            "buffer": (buffer.pos, buffer.full, buffer.observations, buffer.actions, buffer.rewards, buffer.masks),
            "active_heads": model._active_pairs,
            "noise": [(noise.n_calls, noise.sigma) for noise in getattr(model.action_noise, "noises", [model.action_noise])],
            "last_obs": model._last_obs,
        }
    )


def _assert_same(left, right, where="state"):
    if isinstance(left, dict):
        assert left.keys() == right.keys(), where
        for key in left:
            _assert_same(left[key], right[key], f"{where}.{key}")
    elif isinstance(left, (tuple, list)):
        assert len(left) == len(right), where
        for i, (a, b) in enumerate(zip(left, right)):
            _assert_same(a, b, f"{where}[{i}]")
    elif isinstance(left, th.Tensor):
        assert th.equal(left, right), where
    elif isinstance(left, np.ndarray):
        assert np.array_equal(left, right), where
    else:
        assert left == right, where


def _params(model: SOUP) -> th.Tensor:
    return th.nn.utils.parameters_to_vector(model.policy.parameters())


# ---------------------------------------------------------------- kill and resume (default suite)


def test_a_run_killed_with_sigkill_resumes_from_its_last_checkpoint(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    process = subprocess.Popen(
        [sys.executable, str(SCRIPT), str(tmp_path)], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    try:
        deadline = time.time() + 240
        while len(list(tmp_path.glob("rl_model_*_steps.zip"))) < 2:  # written last: two complete checkpoints
            assert process.poll() is None, process.communicate()[0].decode()
            assert time.time() < deadline, "no checkpoints within 240 s"
            time.sleep(0.05)
    finally:
        os.kill(process.pid, signal.SIGKILL)  # mid-training, possibly mid-save
        process.wait()
    assert process.returncode == -signal.SIGKILL

    # 1. sb3-soup's checkpoints: the resumed run is the run that was never killed.
    checkpoint = latest_checkpoint(tmp_path)
    assert checkpoint is not None and checkpoint.training_state is not None
    steps, more = checkpoint.step, 100
    assert steps >= 2 * SAVE_FREQ and steps % SAVE_FREQ == 0
    reference, recorded = make_model(), Recorder(at=steps)
    reference.learn(steps + more, callback=recorded)  # uninterrupted, in this process, without checkpoints

    resumed = load_checkpoint(checkpoint, gym.make("Pendulum-v1"))
    assert isinstance(resumed, SOUP)
    _assert_same(_state(resumed), recorded.snapshot)  # step, buffer and masks, networks, Adam and strategy state, noise
    assert resumed.replay_buffer.pos == steps and resumed.replay_buffer.masks.shape == (2000, 1, 3)
    assert float(resumed.policy.confidence.reward_baseline) != 0.0  # adaptive strategy's state came back
    # the noise's schedule: one draw per step after the warm-up
    assert resumed.action_noise.sigma[0] == pytest.approx(max(0.05, 0.5 * 0.995 ** (steps - KWARGS["learning_starts"])))
    continued = Recorder()
    resumed.learn(more, callback=continued, reset_num_timesteps=False)
    assert resumed.num_timesteps == steps + more
    assert np.array_equal(np.concatenate(continued.actions), np.concatenate(recorded.actions[steps:]))  # same actions
    assert th.equal(_params(resumed), _params(reference))  # same parameters
    _assert_same(_state(resumed)["optimizers"], _state(reference)["optimizers"])

    # 2. SB3's CheckpointCallback (saved mid-step, no env state): the state comes back and training goes on, but the
    # env is reset and the step's transition was not stored yet.
    sb3_checkpoint = latest_checkpoint(tmp_path, name_prefix="sb3")
    assert sb3_checkpoint is not None and sb3_checkpoint.training_state is None
    sb3_steps = sb3_checkpoint.step
    faithful = load_checkpoint(sb3_checkpoint, gym.make("Pendulum-v1"))
    assert faithful.num_timesteps == sb3_steps and faithful.replay_buffer.pos == sb3_steps - 1
    assert 0.3 < faithful.replay_buffer.masks[: sb3_steps - 1].mean() < 0.7  # mask_prob 0.5, per transition
    # one REINFORCE update per training round after the warm-up, rounds done before the step being taken
    confidence_updates = sb3_steps - 1 - KWARGS["learning_starts"]
    confidence_adam = faithful.policy.confidence.optimizer.state_dict()["state"]
    assert all(int(state["step"]) == confidence_updates for state in confidence_adam.values())
    assert faithful._n_updates == confidence_updates
    assert faithful.action_noise.sigma[0] == pytest.approx(max(0.05, 0.5 * 0.995 ** (sb3_steps - KWARGS["learning_starts"])))
    faithful.learn(50, reset_num_timesteps=False)
    assert faithful.num_timesteps == sb3_steps + 50 and faithful.replay_buffer.pos == sb3_steps + 49


# ---------------------------------------------------------------- save, load, continue == uninterrupted (default suite)


@pytest.mark.parametrize(
    "scheme",
    [dict(train_heads="all"), PAPER_UPDATE],
    ids=["every-pair", "paper-active-pair"],  # the active pair: each env's pair, drawn per episode, taken in turn
)
def test_resuming_from_a_checkpoint_gives_the_uninterrupted_run(tmp_path, scheme):
    """Two envs, decayed confidence; SB3's way of resuming (same files) gives another run."""
    kwargs = dict(
        n_heads=3,
        **scheme,
        confidence="decayed",
        confidence_kwargs=dict(decay=0.99),
        learning_starts=30,
        batch_size=16,
    )
    kwargs.update(buffer_size=1000, policy_kwargs=TINY, seed=5)

    def new_env():
        return make_vec_env("Pendulum-v1", n_envs=2, seed=9)

    total, resume_at = 320, 160
    reference, recorded = SOUP("MlpPolicy", new_env(), **kwargs), Recorder(at=resume_at)
    checkpoints = ResumableCheckpointCallback(save_freq=40, save_path=str(tmp_path), keep_last=2)
    reference.learn(total, callback=[recorded, checkpoints])
    assert [checkpoint.step for checkpoint in find_checkpoints(tmp_path)] == [240, 160]  # every 40 * 2 steps, last 2 kept
    checkpoint = next(checkpoint for checkpoint in find_checkpoints(tmp_path) if checkpoint.step == resume_at)

    assert read_training_state(checkpoint.training_state)["rng"] is not None  # the random generators: there only

    resumed = load_checkpoint(checkpoint, new_env())
    _assert_same(_state(resumed), recorded.snapshot)
    assert float(resumed.policy.confidence.n_steps) == resume_at  # the decayed strategy's counter
    continued = Recorder()
    resumed.learn(total - resume_at, callback=continued, reset_num_timesteps=False)
    assert np.array_equal(np.concatenate(continued.actions), np.concatenate(recorded.actions[resume_at // 2 :]))
    assert th.equal(_params(resumed), _params(reference))

    # The same model and buffer files loaded as SB3 does (SOUP.load resets the env, seeds the generators): another run.
    sb3_way = SOUP.load(checkpoint.model, env=new_env())
    sb3_way.load_replay_buffer(checkpoint.replay_buffer)
    other = Recorder()
    sb3_way.learn(total - resume_at, callback=other, reset_num_timesteps=False)
    assert not np.array_equal(np.concatenate(other.actions), np.concatenate(continued.actions))


def test_other_algorithms_resume_exactly_too(tmp_path):
    """The checkpoints are the algorithm's own files plus the training state: TD3 resumes exactly too."""

    def new_model():
        env = DummyVecEnv([lambda: gym.make("Pendulum-v1")])
        noise = NormalActionNoise(np.zeros(1), 0.1 * np.ones(1))  # draws from NumPy's global generator
        return TD3("MlpPolicy", env, learning_starts=20, batch_size=16, policy_kwargs={"net_arch": [16]}, action_noise=noise,
                   seed=0)  # fmt: skip

    reference = new_model()
    reference.learn(100)
    interrupted = new_model()
    interrupted.learn(40)
    save_checkpoint(interrupted, tmp_path, keep_last=1)
    interrupted.learn(20, reset_num_timesteps=False)
    files = save_checkpoint(interrupted, tmp_path, keep_last=1)
    assert [checkpoint.step for checkpoint in find_checkpoints(tmp_path)] == [60]  # the older one deleted
    assert read_training_state(files.training_state)["rng"] is not None
    np.random.seed(1)  # whatever happens in between
    th.manual_seed(1)
    resumed = load_checkpoint(latest_checkpoint(tmp_path), DummyVecEnv([lambda: gym.make("Pendulum-v1")]), TD3)
    resumed.learn(40, reset_num_timesteps=False)
    assert th.equal(_params(resumed), _params(reference))


def test_save_checkpoint_after_learn_continues_exactly_and_save_load_do_not(tmp_path):
    """save_checkpoint after learn() returned resumes exactly; SOUP.save and SOUP.load are SB3's (generators reseeded)."""
    kwargs = dict(n_heads=2, learning_starts=30, batch_size=16, buffer_size=500, policy_kwargs=TINY, seed=2)
    reference = SOUP("MlpPolicy", "Pendulum-v1", **kwargs)
    reference.learn(200)
    interrupted = SOUP("MlpPolicy", "Pendulum-v1", **kwargs)
    interrupted.learn(120)
    files = save_checkpoint(interrupted, tmp_path)
    np.random.seed(0)  # whatever happens in between
    resumed = load_checkpoint(files, gym.make("Pendulum-v1"))
    resumed.learn(80, reset_num_timesteps=False)
    assert th.equal(_params(resumed), _params(reference))

    # the same files, the same live env (not reset): the generators seeded by SOUP.load make another run
    loaded = SOUP.load(files.model, env=interrupted.get_env(), force_reset=False)
    loaded.load_replay_buffer(files.replay_buffer)
    loaded.learn(80, reset_num_timesteps=False)
    assert not th.equal(_params(loaded), _params(reference))


# ---------------------------------------------------------------- the pieces


def test_latest_checkpoint_skips_files_cut_short_by_a_kill(tmp_path):
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=2, learning_starts=20, batch_size=8, buffer_size=300, policy_kwargs=TINY)
    model.learn(150, callback=CheckpointCallback(50, str(tmp_path), save_replay_buffer=True))  # SB3's, writes in place
    assert latest_checkpoint(tmp_path).step == 150
    buffer = tmp_path / "rl_model_replay_buffer_150_steps.pkl"
    buffer.write_bytes(buffer.read_bytes()[:-100])
    assert latest_checkpoint(tmp_path).step == 100  # the newest buffer is cut short
    zip_file = tmp_path / "rl_model_100_steps.zip"
    zip_file.write_bytes(zip_file.read_bytes()[:-50])
    assert latest_checkpoint(tmp_path).step == 50  # then the newest zip
    (tmp_path / "rl_model_replay_buffer_50_steps.pkl").unlink()
    assert latest_checkpoint(tmp_path) is None and latest_checkpoint(tmp_path, need_replay_buffer=False).step == 50

    # sb3-soup's callback writes atomically, the zip last, and clears what a killed process left half-written
    stale = tmp_path / ".rl_model_200_steps.zip.tmp-12345"
    stale.write_bytes(b"PK\x03\x04 half")
    orphan = tmp_path / "rl_model_replay_buffer_250_steps.pkl"  # killed before the zip of its checkpoint
    orphan.write_bytes(b"\x80")
    model.learn(100, callback=ResumableCheckpointCallback(50, str(tmp_path)), reset_num_timesteps=False)
    assert not stale.exists() and not orphan.exists()
    assert latest_checkpoint(tmp_path).step == 200  # the last one between two rollouts
    assert not list(tmp_path.glob(".*"))


def test_the_env_state_round_trip_keeps_mujoco_and_monitor_state():
    """MuJoCo envs pickle as their constructor arguments (EzPickle): the state is saved attribute by attribute."""
    pytest.importorskip("mujoco")

    def new_env():
        return make_vec_env("Hopper-v4", n_envs=1, seed=0)

    live = new_env()
    live.reset()
    for _ in range(30):
        live.step(np.array([live.action_space.sample()]))
    restored = new_env()
    set_env_state(restored, get_env_state(live))
    rng = np.random.default_rng(0)
    for _ in range(150):  # through at least one episode end (auto-reset draws from the env's np_random)
        action = rng.uniform(-1, 1, size=(1, 3)).astype(np.float32)
        obs_a, reward_a, done_a, info_a = live.step(action)
        obs_b, reward_b, done_b, info_b = restored.step(action)
        assert np.array_equal(obs_a, obs_b) and np.array_equal(reward_a, reward_b) and np.array_equal(done_a, done_b)
        if done_a[0]:
            assert info_a[0]["episode"]["r"] == info_b[0]["episode"]["r"]  # the Monitor's running episode too


def test_env_states_that_cannot_be_restored_are_refused_or_left_out():
    with pytest.raises(EnvStateError, match="the environment is not built like the saved one"):
        set_env_state(make_vec_env("Pendulum-v1", n_envs=2), get_env_state(make_vec_env("Pendulum-v1", n_envs=1)))

    class NotPicklable(gym.Wrapper):
        def __init__(self, env):
            super().__init__(env)
            self.handle = (lambda: (yield))()  # a generator: does not pickle

    with pytest.raises(EnvStateError, match="does not pickle"):
        get_env_state(DummyVecEnv([lambda: NotPicklable(gym.make("Pendulum-v1"))]))


def test_a_training_state_of_another_format_is_refused(tmp_path):
    path = tmp_path / "state.pkl"
    save_training_state(SOUP("MlpPolicy", "Pendulum-v1", n_heads=2, buffer_size=100, policy_kwargs=TINY), path)
    state = read_training_state(path)
    assert state["format"] == TRAINING_STATE_FORMAT == 3 and state["rng"] is not None
    state["format"] = 2  # 0.2.0a0 before the random generators left SOUP's model zip
    path.write_bytes(pickle.dumps(state))
    with pytest.raises(ValueError, match=r"state\.pkl is a training state of format 2, written by another sb3-soup; this one"):
        read_training_state(path)


def test_a_checkpoint_saved_mid_step_leaves_the_env_out(tmp_path):
    class SaveMidStep(BaseCallback):
        env_saved = None

        def _on_step(self) -> bool:  # inside a step: the env is one step ahead of the model's last observation
            if self.num_timesteps == 10:
                self.env_saved = save_training_state(self.model, tmp_path / "state.pkl")
            return True

    callback = SaveMidStep()
    model = SOUP("MlpPolicy", "Pendulum-v1", n_heads=2, buffer_size=100, policy_kwargs=TINY)
    with pytest.warns(UserWarning, match="stepped past the model's last observation .* not an exact continuation"):
        model.learn(12, callback=callback)
    assert callback.env_saved is False


def test_the_experiment_runner_resumes_exactly(tmp_path):
    """The runner's checkpoints share the mechanism: stopped and resumed, a run ends where the uninterrupted one does."""
    from sb3_soup.experiments import logs
    from sb3_soup.experiments.grid import build_grid, parse_overrides
    from sb3_soup.experiments.runner import FINAL_MODEL, run_one

    net_arch = TINY["net_arch"]
    overrides = parse_overrides(
        ["learning_starts=30", "batch_size=16", "buffer_size=1000", f"policy_kwargs=dict(net_arch={net_arch})"]
    )

    def spec(folder, **kwargs):
        [run] = build_grid(
            "Pendulum-v1",
            tmp_path / folder,
            models=["soup"],
            heads=[3],
            seeds=[0],
            timesteps=230,
            overrides=overrides,
            eval_freq=50,
            eval_episodes=1,
            **kwargs,
        )
        return dataclasses.asdict(run)

    assert run_one(spec("whole", checkpoint_freq=0))["status"] == "finished"
    assert run_one(spec("parts", checkpoint_freq=100, stop_after=130))["status"] == "interrupted"  # stops at 130
    assert run_one(spec("parts", checkpoint_freq=100))["status"] == "finished"
    whole, parts = (next((tmp_path / folder).glob(f"*/seed_0/{FINAL_MODEL}")) for folder in ("whole", "parts"))
    assert th.equal(_params(SOUP.load(whole)), _params(SOUP.load(parts)))
    # the episode in progress at the stop went on: the Monitor logs the same episodes
    assert logs.read_monitor(whole.parent)[["r", "l"]].equals(logs.read_monitor(parts.parent)[["r", "l"]])
    # and the same evaluations and training logs (but for the wall-clock columns)
    assert logs.read_evaluations(whole.parent)["step"].tolist() == [50, 100, 150, 200]
    assert logs.read_evaluations(whole.parent).equals(logs.read_evaluations(parts.parent))
    clock = ["time/fps", "time/time_elapsed"]
    progress = logs.read_progress(whole.parent).drop(columns=clock)
    assert progress["time/total_timesteps"].tolist() == [200]  # log_interval=1: at the end of the first episode
    assert progress.equals(logs.read_progress(parts.parent).drop(columns=clock))
