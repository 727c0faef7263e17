"""
RL Zoo integration: the registration (``sb3_soup.zoo``), the import hook shipped as ``sb3_soup_zoo.pth``, and the
Zoo's own command lines (train, enjoy, plots, record_video, -optimize on a shared sqlite study) run as subprocesses
with tiny budgets, from a folder outside the repository (so they rely on the installed hook).
"""

import importlib.metadata
import importlib.util
import inspect
import os
import re
import site
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from gymnasium import spaces
from scripts import load_script

import _sb3_soup_zoo_hook
from sb3_soup import paper_settings, zoo
from sb3_soup.presets import PAPER_NOISE, hyperparams_file, paper_hyperparams

REPO = Path(__file__).resolve().parent.parent
ENV_ID = "Pendulum-v1"
# A few hundred steps with updates from step 100: enough to build, train, save and reload SOUP.
TINY = ["-n", "300", "--hyperparams", "learning_starts:100", "batch_size:32", "--seed", "0"]


def run(args: list[str], cwd: Path, hook: bool = True, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run ``python ARGS`` in ``cwd`` with the hook enabled (the default of an installed sb3-soup) or disabled."""
    env = dict(os.environ, MPLBACKEND="Agg", OMP_NUM_THREADS="1", SDL_VIDEODRIVER="dummy")
    env.pop(_sb3_soup_zoo_hook.ENV_VAR, None)
    if not hook:
        env[_sb3_soup_zoo_hook.ENV_VAR] = "0"
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def check(result: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    output = f"stdout:\n{result.stdout[-3000:]}\nstderr:\n{result.stderr[-3000:]}"
    assert result.returncode == 0, f"exit code {result.returncode}\n{output}"
    return result


def saved_config(folder: Path) -> dict:
    """The hyper-parameters the Zoo saved for the first run of ``folder``."""
    path = folder / "soup" / f"{ENV_ID}_1" / ENV_ID / "config.yml"
    return dict(yaml.load(path.read_text(), Loader=yaml.UnsafeLoader))


def test_hook_watches_the_modules_the_registration_needs():
    assert _sb3_soup_zoo_hook.HOOKED_MODULES == set(zoo.HOOKED_MODULES)


@pytest.mark.parametrize(("value", "enabled"), [(None, True), ("1", True), ("0", False), ("false", False), ("OFF", False)])
def test_hook_env_var(monkeypatch, value, enabled):
    if value is None:
        monkeypatch.delenv(_sb3_soup_zoo_hook.ENV_VAR, raising=False)
    else:
        monkeypatch.setenv(_sb3_soup_zoo_hook.ENV_VAR, value)
    assert _sb3_soup_zoo_hook.enabled() is enabled


def test_registration_is_idempotent():
    from rl_zoo3.exp_manager import ExperimentManager
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
    from rl_zoo3.utils import ALGOS

    from sb3_soup import SOUP
    from sb3_soup.zoo_hyperparams import convert_soup_params, sample_soup_params

    zoo.register()
    init = ExperimentManager.__init__
    algos = dict(ALGOS)
    zoo.register()
    zoo.register()
    assert ALGOS["soup"] is SOUP and ALGOS == algos
    assert HYPERPARAMS_SAMPLER["soup"] is sample_soup_params
    assert HYPERPARAMS_CONVERTER["soup"] is convert_soup_params
    # wrapped once: the wrapper wraps the Zoo's own __init__
    assert ExperimentManager.__init__ is init
    assert not hasattr(init.__wrapped__, "__wrapped__")


def test_paper_entries_get_their_decaying_noise(tmp_path):
    """soup_paper.yml's noise_type 'decaying_normal' (noise_std, noise_decay, noise_std_min) is built by the Zoo hook."""
    import argparse

    from rl_zoo3.exp_manager import ExperimentManager

    from sb3_soup import DecayingNormalActionNoise

    zoo.register()
    zoo.register()  # wrapped once
    entry = yaml.safe_load(hyperparams_file("soup_paper").read_text())["Hopper-v4"]
    conf = tmp_path / "paper.yml"
    conf.write_text(yaml.safe_dump({ENV_ID: {**entry, "n_heads": 2, "buffer_size": 1000, "batch_size": 16}}))
    manager = ExperimentManager(
        argparse.Namespace(), "soup", ENV_ID, str(tmp_path / "logs"), n_timesteps=40, eval_freq=-1, config=str(conf),
        hyperparams=dict(learning_starts=20), seed=0, verbose=0, device="cpu",
    )  # fmt: skip
    setup = manager.setup_experiment()
    assert setup is not None
    noise = setup[0].action_noise
    assert isinstance(noise, DecayingNormalActionNoise) and (noise.decay, noise.sigma_min) == (0.999995, 0.05)
    np.testing.assert_array_equal(noise.sigma, [0.2])
    setup[0].learn(40)
    assert noise.n_calls == 20


def test_default_conf_file_only_for_soup_without_conf_file(tmp_path):
    import argparse

    from rl_zoo3.exp_manager import ExperimentManager

    zoo.register()
    args = argparse.Namespace()
    folder = str(tmp_path)
    assert ExperimentManager(args, "soup", ENV_ID, folder).config == str(zoo.DEFAULT_CONF_FILE)
    assert ExperimentManager(args, "soup", ENV_ID, folder, config="mine.yml").config == "mine.yml"
    assert ExperimentManager(args, "td3", ENV_ID, folder).config.endswith(os.path.join("hyperparams", "td3.yml"))


def test_registration_failure_is_a_warning(monkeypatch):
    import rl_zoo3.utils

    def broken(module):
        raise RuntimeError("boom")

    monkeypatch.setattr(zoo, "on_import", broken)
    with pytest.warns(RuntimeWarning, match=r"could not register SOUP.*rl_zoo3\.utils.*boom"):
        _sb3_soup_zoo_hook._register(rl_zoo3.utils)


def test_hyperparams_file_has_the_issues_envs():
    entries = yaml.safe_load(zoo.DEFAULT_CONF_FILE.read_text())
    for env in ("Hopper", "Walker2d", "HalfCheetah", "Ant", "InvertedPendulum"):
        for version in ("v4", "v5"):
            assert f"{env}-{version}" in entries
    assert "Pendulum-v1" in entries
    for values in entries.values():
        if values.get("replay_buffer_class") == "HerReplayBuffer":  # goal-conditioned: the Zoo's HER entries' values
            continue
        # SOUP's defaults, only the budget set (confidence and mask_prob left so that `--hyperparams preset:...` can set them)
        assert set(values) <= {"n_timesteps", "policy", "n_heads", "learning_starts"}
    assert entries["Hopper-v4"]["learning_starts"] == 10_000 and entries["Walker2d-v5"] == entries["Hopper-v4"]


def repo_soup_entries() -> dict:
    """The repository's soup.yml (the installed one may be another checkout's)."""
    return yaml.safe_load((REPO / "hyperparams" / "soup.yml").read_text())


def test_pandareach_entry_is_the_her_benchmarks_settings():
    """soup.yml's PandaReach-v3 (the Zoo's HER entry for SOUP) is what benchmarks/her_panda.py measured."""
    her_panda = load_script("benchmarks/her_panda.py")
    entry = repo_soup_entries()[her_panda.ENV_ID]
    assert entry["policy"] == "MultiInputPolicy" and entry["replay_buffer_class"] == "HerReplayBuffer"
    from sb3_soup import SOUP

    defaults = inspect.signature(SOUP.__init__).parameters  # (tau: SOUP's default, the benchmark's value)
    for key, value in her_panda.COMMON.items():
        assert entry.get(key, defaults[key].default) == value, key
    assert eval(entry["replay_buffer_kwargs"]) == her_panda.HER_KWARGS
    assert eval(entry["policy_kwargs"]) == dict(net_arch=her_panda.SOUP_ARCH)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_her_entry_trains_with_soup_from_the_command_line(tmp_path):
    """`rl_zoo3.train --algo soup` with soup.yml's PandaReach-v3 entry (HerReplayBuffer) on a registered goal env."""
    env_id = "SOUPBitFlipping-v0"  # tests/goal_env.py: SB3's BitFlippingEnv, continuous actions (no panda-gym needed)
    config = tmp_path / "soup_her.yml"
    config.write_text(yaml.safe_dump({env_id: repo_soup_entries()["PandaReach-v3"]}))
    tests = str(Path(__file__).resolve().parent)
    env = dict(os.environ, MPLBACKEND="Agg", OMP_NUM_THREADS="1", PYTHONPATH=os.pathsep.join([tests, *sys.path]))
    env.pop(_sb3_soup_zoo_hook.ENV_VAR, None)
    args = ["-m", "rl_zoo3.train", "--algo", "soup", "--env", env_id, "--gym-packages", "goal_env", "--conf-file", str(config)]
    args += ["-n", "120", "--hyperparams", "learning_starts:40", "batch_size:16", "--eval-freq", "-1", "--seed", "0"]
    result = subprocess.run([sys.executable, *args, "-f", str(tmp_path)], cwd=tmp_path, env=env, capture_output=True,
                            text=True, timeout=300)  # fmt: skip
    check(result)
    run_dir = tmp_path / "soup" / f"{env_id}_1"
    saved = dict(yaml.load((run_dir / env_id / "config.yml").read_text(), Loader=yaml.UnsafeLoader))
    assert saved["replay_buffer_class"] == "HerReplayBuffer" and saved["gamma"] == 0.95
    import goal_env  # noqa: F401  (registers the env here too)
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_soup import SOUP, BootstrappedHerReplayBuffer

    model = SOUP.load(run_dir / f"{env_id}.zip", env=make_vec_env(env_id), device="cpu")
    assert model.num_timesteps == 120 and model.gamma == 0.95
    assert issubclass(model.replay_buffer_class, BootstrappedHerReplayBuffer)
    assert model.replay_buffer_kwargs["n_sampled_goal"] == 4 and "n_updates" in result.stdout


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_pandareach_entry_trains_from_the_command_line(tmp_path):
    """soup.yml's PandaReach-v3 through the Zoo on panda-gym itself (pip install "sb3-soup[her]"), a short run."""
    pytest.importorskip("panda_gym")
    args = ["-m", "rl_zoo3.train", "--algo", "soup", "--env", "PandaReach-v3", "--gym-packages", "panda_gym"]
    args += ["--conf-file", str(REPO / "hyperparams" / "soup.yml"), "-n", "300", "--hyperparams", "learning_starts:100"]
    check(run([*args, "--eval-freq", "-1", "--seed", "0", "-f", str(tmp_path)], tmp_path, timeout=800))
    assert (tmp_path / "soup" / "PandaReach-v3_1" / "PandaReach-v3.zip").is_file()


def test_paper_hyperparams_file_is_paper_settings():
    """soup_paper.yml's MuJoCo entries are sb3_soup.paper_settings() (Section 5 of the paper), with the Zoo's warm-up
    (and the noise as the Zoo's keys, sb3_soup.presets.paper_hyperparams())."""
    entries = yaml.safe_load(hyperparams_file("soup_paper").read_text())
    paper = entries["Hopper-v4"]
    assert (paper["learning_rate"], paper["critic_learning_rate"], paper["gamma"], paper["tau"]) == (1e-4, 3e-4, 0.99, 1e-3)
    assert (paper["batch_size"], paper["buffer_size"], paper["n_heads"]) == (1024, 1_000_000, 10)
    settings = paper_hyperparams()
    assert (
        {key: settings[key] for key in PAPER_NOISE}
        == PAPER_NOISE
        == dict(noise_type="decaying_normal", noise_std=0.2, noise_decay=0.999995, noise_std_min=0.05)
    )
    assert {key: value for key, value in paper_settings(spaces.Box(-1, 1, (2,))).items() if key != "action_noise"} == {
        key: value for key, value in settings.items() if key not in PAPER_NOISE
    }
    for key, value in paper.items():
        if key == "policy_kwargs":
            assert eval(value) == settings[key]
        elif key not in ("n_timesteps", "policy", "n_heads", "learning_starts"):
            assert settings[key] == value, key
    assert entries["Walker2d-v5"] == paper
    assert all("confidence" not in values and "mask_prob" not in values for values in entries.values())


def test_pendulum_entry_is_the_demos_settings():
    """soup.yml's Pendulum-v1 is what `make demo` and the learning test train (checked against drift)."""
    from sb3_soup.demo import PENDULUM_SETTINGS

    entry = yaml.safe_load(zoo.DEFAULT_CONF_FILE.read_text())["Pendulum-v1"]
    assert {key: entry[key] for key in PENDULUM_SETTINGS} == PENDULUM_SETTINGS
    assert set(entry) - set(PENDULUM_SETTINGS) == {"n_timesteps", "policy", "n_heads"}


def test_sampled_hyperparameters_build_soup():
    import optuna

    from sb3_soup import SOUP
    from sb3_soup.zoo_hyperparams import convert_soup_params, sample_soup_params

    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0), direction="maximize")
    seen, seen_layers = set(), set()
    for _ in range(12):
        trial = study.ask()
        kwargs = sample_soup_params(trial, n_actions=1, n_envs=1, additional_args={})
        # what --trial-id rebuilds from the stored values is what the trial trained (the Zoo builds the noise of its keys)
        converted = convert_soup_params(trial.params)
        assert converted.pop("noise_type") == "decaying_normal" and kwargs["action_noise"].decay == 1.0
        np.testing.assert_array_equal(kwargs.pop("action_noise").sigma, [converted.pop("noise_std")])
        assert converted == kwargs
        assert 64 <= kwargs["batch_size"] <= 1024 and 0.97 <= kwargs["gamma"] < 1
        assert kwargs["gradient_steps"] == kwargs["train_freq"]
        assert ("confidence_kwargs" in kwargs) == (kwargs["confidence"] == "adaptive")
        assert kwargs["policy_delay"] in (1, 2) and kwargs["target_policy_noise"] in (0.0, 0.2)
        assert kwargs["policy_kwargs"]["net_arch"]["qf_action_layer"] == trial.params["qf_action_layer"]
        seen.add(kwargs["confidence"])
        seen_layers.add(trial.params["qf_action_layer"])
        model = SOUP(env=ENV_ID, policy="MlpPolicy", buffer_size=1000, **converted)
        assert model.policy is not None
        study.tell(trial, 0.0)
    assert len(seen) > 1 and seen_layers == {0, 1}


def test_a_trial_sampled_before_the_delay_and_smoothing_joined_the_space_is_rebuilt_as_it_trained():
    from sb3_soup.zoo_hyperparams import convert_soup_params

    old_trial = dict(train_heads="all", target_q="min_pair", n_heads=5)  # before 0.2.0: no delay, no smoothing
    assert convert_soup_params(old_trial) == dict(old_trial, policy_delay=1, target_policy_noise=0.0)
    new_trial = dict(old_trial, policy_delay=2, target_policy_noise=0.2)
    assert convert_soup_params(new_trial) == new_trial


def test_a_trial_sampled_before_the_critics_action_layer_joined_the_space_is_rebuilt_as_it_trained():
    from sb3_soup.zoo_hyperparams import convert_soup_params

    def action_layer(trial: dict) -> int:
        return convert_soup_params(trial)["policy_kwargs"]["net_arch"]["qf_action_layer"]

    for net_arch in ("small", "paper", "big"):
        # before: the action at the critic's second layer, whatever the default
        assert action_layer(dict(net_arch=net_arch)) == 1
        assert action_layer(dict(net_arch=net_arch, qf_action_layer=0)) == 0


def test_installed_distribution_ships_the_pth_file():
    """Whatever the install (wheel or editable), pip's RECORD lists the .pth: `pip uninstall` removes it."""
    files = {str(path) for path in importlib.metadata.files("sb3-soup") or []}
    assert "sb3_soup_zoo.pth" in files
    pth = importlib.metadata.distribution("sb3-soup").locate_file("sb3_soup_zoo.pth")
    assert Path(pth).read_text().strip() == "import _sb3_soup_zoo_hook"


def test_startup_installs_the_finder_and_imports_nothing_heavy(tmp_path):
    code = (
        "import sys; import _sb3_soup_zoo_hook as h; "
        "print(h.ZooFinder in sys.meta_path, sorted(m for m in ('torch', 'rl_zoo3', 'sb3_soup', 'numpy') if m in sys.modules))"
    )
    assert check(run(["-c", code], tmp_path)).stdout.split() == ["True", "[]"]
    assert check(run(["-c", code], tmp_path, hook=False)).stdout.split() == ["False", "[]"]


def test_startup_cost_under_two_ms():
    """-X importtime of the hook module at start-up (bytecode compiled, as after a wheel install), as the benchmark does."""
    benchmark = load_script("benchmarks/zoo_startup.py")
    benchmark.compile_hook()
    costs = [benchmark.hook_import_us() for _ in range(5)]
    assert min(costs) < 2000, costs


def test_hook_disabled_zoo_refuses_soup(tmp_path):
    refused = run(["-m", "rl_zoo3.train", "--algo", "soup", "--env", ENV_ID, *TINY, "-f", str(tmp_path)], tmp_path, hook=False)
    assert refused.returncode == 2
    assert "invalid choice: 'soup'" in refused.stderr
    assert not (tmp_path / "soup").exists()


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_hook_disabled_plain_entry_point_trains(tmp_path):
    args = ["-m", "sb3_soup.train", "--algo", "soup", "--env", ENV_ID, *TINY, "--eval-freq", "-1", "-f", str(tmp_path)]
    check(run(args, tmp_path, hook=False))
    assert (tmp_path / "soup" / f"{ENV_ID}_1" / f"{ENV_ID}.zip").is_file()


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """`python -m rl_zoo3.train --algo soup` without --conf-file, with two evaluations (for the plots)."""
    folder = tmp_path_factory.mktemp("zoo_logs")
    args = ["-m", "rl_zoo3.train", "--algo", "soup", "--env", ENV_ID, *TINY, "--eval-freq", "150", "--eval-episodes", "2"]
    result = check(run([*args, "-f", str(folder)], folder))
    assert f"Loading hyperparameters from: {zoo.DEFAULT_CONF_FILE}" in result.stdout
    return folder


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_train_without_conf_file(trained):
    run_dir = trained / "soup" / f"{ENV_ID}_1"
    assert (run_dir / f"{ENV_ID}.zip").is_file()
    assert (run_dir / "evaluations.npz").is_file()
    config = saved_config(trained)
    # soup.yml's Pendulum-v1 entry (the budget; the rest is SOUP's defaults), with the command line's overrides
    assert config["n_heads"] == 5 and "gamma" not in config
    assert config["learning_starts"] == 100 and config["batch_size"] == 32

    from sb3_soup import SOUP

    model = SOUP.load(run_dir / f"{ENV_ID}.zip")
    assert model.num_timesteps == 300 and model.gamma == 0.99 and model.batch_size == 32


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_enjoy_the_trained_agent(trained):
    args = ["--algo", "soup", "--env", ENV_ID, "-f", str(trained), "--no-render", "-n", "250", "--deterministic"]
    for module in ("rl_zoo3.enjoy", "sb3_soup.enjoy"):
        result = check(run(["-m", module, *args], trained))
        assert "Episode Reward:" in result.stdout


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_plots_of_the_training_folder(trained):
    output = trained / "all_plots"
    plot_args = ["-a", "soup", "-e", ENV_ID, "-f", str(trained)]
    check(run(["-m", "rl_zoo3.plots.all_plots", *plot_args, "--no-display", "-o", str(output)], trained))
    import pickle

    with open(f"{output}.pkl", "rb") as file:
        results = pickle.load(file)
    assert ENV_ID in results
    check(run(["-m", "rl_zoo3.plots.plot_train", *plot_args, "-w", "1"], trained))


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_record_video(trained):
    missing = [name for name in ("moviepy", "pygame") if importlib.util.find_spec(name) is None]
    if missing:
        pytest.skip(f"record_video needs {missing} (pip install 'sb3-soup[zoo]')")
    videos = trained / "videos"
    args = ["-m", "rl_zoo3.record_video", "--algo", "soup", "--env", ENV_ID, "-f", str(trained), "-n", "50", "-o", str(videos)]
    check(run(args, trained))
    assert list(videos.glob("*.mp4"))


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_optimize_two_workers_share_one_sqlite_study(tmp_path):
    import optuna

    storage = f"sqlite:///{tmp_path / 'study.db'}"
    # Created once before the workers start: two processes creating the schema of a new sqlite file at once collide.
    optuna.create_study(storage=storage, study_name="soup", direction="maximize")
    env = dict(os.environ, MPLBACKEND="Agg", OMP_NUM_THREADS="1")
    env.pop(_sb3_soup_zoo_hook.ENV_VAR, None)
    args = ["-m", "rl_zoo3.train", "--algo", "soup", "--env", ENV_ID, "-optimize", "--storage", storage]
    args += ["--study-name", "soup", "--n-trials", "1", "--n-jobs", "1", "--n-startup-trials", "1", "--n-evaluations", "1"]
    args += ["--eval-episodes", "1", "--no-optim-plots", "-n", "300", "--hyperparams", "learning_starts:100"]
    workers = [
        subprocess.Popen(
            [sys.executable, *args, "-f", str(tmp_path / f"worker{i}"), "--seed", str(i)],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in range(2)
    ]
    outputs = [worker.communicate(timeout=600)[0] for worker in workers]
    for worker, output in zip(workers, outputs):
        assert worker.returncode == 0, output[-3000:]
    trials = optuna.load_study(study_name="soup", storage=storage).trials
    assert len(trials) == 2
    assert all(trial.state in (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED) for trial in trials)

    # --trial-id trains with a trial's values, converted back by the registered converter (the Zoo ignores
    # --trial-id 0: it tests `if self.trial_id`)
    trial = trials[1]
    retrain = ["-m", "rl_zoo3.train", "--algo", "soup", "--env", ENV_ID, *TINY, "--eval-freq", "-1"]
    retrain += ["-f", str(tmp_path / "best"), "--storage", storage, "--study-name", "soup", "--trial-id", "1"]
    check(run(retrain, tmp_path))
    config = saved_config(tmp_path / "best")
    assert config["n_heads"] == trial.params["n_heads"]
    assert config["confidence"] == trial.params["confidence"]


def wheel_with_hook(tmp_path: Path) -> Path:
    """Build sb3-soup's wheel and check that it holds (and its RECORD lists) the hook, the .pth and soup.yml."""
    wheels = tmp_path / "wheels"
    check(run(["-m", "pip", "wheel", "--no-deps", str(REPO), "-w", str(wheels), "-q"], tmp_path))
    (wheel,) = wheels.glob("sb3_soup-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        record = next(archive.read(name).decode() for name in names if name.endswith(".dist-info/RECORD"))
    shipped = ("sb3_soup/hyperparams/soup.yml", "sb3_soup/hyperparams/soup_paper.yml")
    for name in ("sb3_soup_zoo.pth", "_sb3_soup_zoo_hook.py", *shipped, "sb3_soup/zoo.py"):
        assert name in names
        assert re.search(rf"^{re.escape(name)},sha256=", record, re.MULTILINE)
    return wheel


def venv_over_this_environment(target: Path) -> str:
    """
    A throwaway venv whose own site-packages come first and which then sees the packages of the interpreter running
    the tests (torch, SB3, ...), whether that is a virtual environment, a conda env or a bare system Python.

    ``EnvBuilder(system_site_packages=True)`` would expose the *base* interpreter's site-packages instead, which lack
    the packages when the tests run in a virtual environment. Here the venv is created isolated and a ``.pth`` file in
    its site-packages runs ``site.addsitedir`` on each site-packages folder of the running interpreter, the way Python
    adds the system site to a venv: after the venv's own, with their ``.pth`` files processed.

    :param target: the venv's folder
    :return: the venv's python
    """
    venv.EnvBuilder(system_site_packages=False, with_pip=False).create(target)
    python = target / "bin" / "python"
    own_site = check(
        subprocess.run([str(python), "-c", "import site; print(site.getsitepackages()[0])"], capture_output=True, text=True)
    ).stdout.strip()
    ours = [*site.getsitepackages(), *([site.getusersitepackages()] if site.ENABLE_USER_SITE else [])]
    lines = "".join(f"import site; site.addsitedir({folder!r})\n" for folder in ours if Path(folder).is_dir())
    (Path(own_site) / "_running_environment.pth").write_text(lines)
    return str(python)


def test_throwaway_venv_sees_this_environment(tmp_path):
    python = venv_over_this_environment(tmp_path / "venv")
    where = "import sys, yaml, pytest; print(sys.prefix, yaml.__file__)"
    prefix, yaml_file = check(subprocess.run([python, "-c", where], capture_output=True, text=True)).stdout.split()
    assert Path(prefix) == tmp_path / "venv"  # its own environment...
    assert Path(yaml_file) == Path(yaml.__file__)  # ...over the packages of the one running the tests


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("mode", ["wheel", "editable"])
def test_install_ships_hook_and_uninstall_removes_it(tmp_path, mode):
    """Install (no deps) into a fresh venv over this environment, check the hook registers SOUP, uninstall."""
    target = tmp_path / "venv"
    python = venv_over_this_environment(target)
    pip = ["-m", "pip", "--python", python]
    if mode == "wheel":
        check(run([*pip, "install", "--no-deps", "-q", str(wheel_with_hook(tmp_path))], tmp_path))
        home = target
    else:
        check(run([*pip, "install", "--no-deps", "-q", "-e", str(REPO)], tmp_path))
        home = REPO
    (site,) = target.glob("lib/python*/site-packages")
    assert (site / "sb3_soup_zoo.pth").is_file()
    where = "import sys, _sb3_soup_zoo_hook as h, sb3_soup; print(h.__file__, sb3_soup.__file__, h.ZooFinder in sys.meta_path)"
    hook_file, package_file, installed = check(
        subprocess.run([python, "-c", where], cwd=tmp_path, capture_output=True, text=True)
    ).stdout.split()
    assert hook_file.startswith(str(home)) and package_file.startswith(str(home)) and installed == "True"
    # the hook alone registers SOUP: nothing imports sb3_soup here
    registered = "import rl_zoo3; print(rl_zoo3.ALGOS['soup'].__module__)"
    out = check(subprocess.run([python, "-c", registered], cwd=tmp_path, capture_output=True, text=True)).stdout
    assert out.split()[-1] == "sb3_soup.soup"

    check(run([*pip, "uninstall", "-y", "-q", "sb3-soup"], tmp_path))
    assert not (site / "sb3_soup_zoo.pth").exists()
    assert not (site / "_sb3_soup_zoo_hook.py").exists()
