"""
The RL Zoo's TD3 and DDPG entries trained as SOUP: the drop-in promise measured on the hyper-parameters users run.

Every entry of the installed rl_zoo3's ``hyperparams/td3.yml`` and ``ddpg.yml`` is written, unchanged, to a one-entry
YAML file and trained for a few hundred steps with ``python -m rl_zoo3.train --algo soup -conf FILE``, and with the
entry's own algorithm as the control (an entry the control fails on is SB3's or the Zoo's, not SOUP's). An entry whose
environment cannot be made and reset here (Box2D, PyBullet, ...) is listed as skipped, with the reason. ``--forms``
adds SB3 argument forms that no entry uses (``optimizer_kwargs``, integral floats, ...), each on Pendulum-v1.

    python benchmarks/zoo_entries.py --out /tmp/zoo-entries          # every entry, SOUP and its control
    python benchmarks/zoo_entries.py --only Hopper-v4 Pendulum-v1 --forms

Prints one row per (file, entry) and writes ``results.json`` (each run's command, exit code, seconds and error tail)
into ``--out``. Exit code 1 if any SOUP run fails where its control does not.
"""

import argparse
import functools
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import rl_zoo3
import yaml

# SB3 forms that no Zoo entry uses, each an entry on Pendulum-v1 (control: TD3)
FORMS: dict[str, dict[str, Any]] = {
    "optimizer_kwargs amsgrad": dict(policy_kwargs="dict(optimizer_kwargs=dict(amsgrad=True))"),
    "optimizer_kwargs AdamW-style": dict(
        policy_kwargs="dict(optimizer_kwargs=dict(weight_decay=1e-4, decoupled_weight_decay=True))"
    ),
    "optimizer_class AdamW": dict(policy_kwargs="dict(optimizer_class=th.optim.AdamW)"),
    "policy_delay 2.0": dict(policy_delay=2.0),
    "net_arch dict pi/qf, ReLU": dict(policy_kwargs="dict(net_arch=dict(pi=[64, 64], qf=[400, 300]), activation_fn=nn.ReLU)"),
    "share_features_extractor": dict(policy_kwargs="dict(share_features_extractor=True)"),
    "train_freq episode, gradient_steps -1": dict(train_freq=[1, "episode"], gradient_steps=-1),
    "n_envs 2, normalize": dict(n_envs=2, normalize=True),
    "n_steps 3": dict(n_steps=3),
}


def zoo_entries(algo: str) -> dict[str, dict[str, Any]]:
    path = Path(rl_zoo3.__file__).parent / "hyperparams" / f"{algo}.yml"
    return yaml.load(path.read_text(), Loader=yaml.UnsafeLoader)  # the Zoo's own loader (anchors and merges)


@functools.cache  # td3.yml and ddpg.yml name the same envs
def env_problem(env_id: str) -> str | None:
    """None if ``env_id`` can be made and reset here, else why not."""
    try:
        env = gym.make(env_id)
        env.reset(seed=0)
        env.close()
    except Exception as error:  # any failure to make or reset the env is a reason to skip its entry
        return f"{type(error).__name__}: {str(error).splitlines()[0][:120]}"
    return None


def train(algo: str, env_id: str, entry: dict[str, Any], folder: Path, steps: int) -> dict[str, Any]:
    conf = folder / "confs" / f"{algo}-{env_id}-{abs(hash(json.dumps(entry, sort_keys=True, default=str)))}.yml"
    conf.parent.mkdir(parents=True, exist_ok=True)
    conf.write_text(yaml.dump({env_id: entry}, sort_keys=False))
    command = [sys.executable, "-m", "rl_zoo3.train", "--algo", algo, "--env", env_id, "-conf", str(conf)]
    command += ["-n", str(steps), "--eval-freq", "-1", "--seed", "0", "--num-threads", "1", "--device", "cpu"]
    command += ["--log-folder", str(folder / "logs"), "-params", "learning_starts:100", "batch_size:32"]
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, env=dict(os.environ, OMP_NUM_THREADS="1"))
    tail = "\n".join((result.stdout + result.stderr).strip().splitlines()[-6:]) if result.returncode else ""
    return dict(command=command, returncode=result.returncode, seconds=round(time.perf_counter() - start, 1), error=tail)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("zoo-entries"), help="folder for the YAML files, logs, results.json")
    parser.add_argument("--steps", type=int, default=300, help="env steps per run (100 random, then training)")
    parser.add_argument("--only", nargs="*", help="env ids (entries) to run; default: all")
    parser.add_argument("--forms", action="store_true", help="also the SB3 forms no entry uses, on Pendulum-v1")
    args = parser.parse_args()
    rows = []
    cases = [(algo, env_id, entry) for algo in ("td3", "ddpg") for env_id, entry in zoo_entries(algo).items()]
    if args.forms:
        base = zoo_entries("td3")["Pendulum-v1"]
        cases += [("td3", "Pendulum-v1", dict(base, **form, _form=name)) for name, form in FORMS.items()]
    for algo, env_id, entry in cases:
        if args.only and env_id not in args.only and "_form" not in entry:
            continue
        form = entry.pop("_form", None)
        name = f"{algo}.yml {env_id}" + (f" + {form}" if form else "")
        target = env_id if env_id != "default" else "InvertedPendulum-v4"  # the default entry, on a task it fits
        problem = env_problem(target)
        if problem:
            rows.append(dict(entry=name, skipped=problem))
            print(f"{name:60s} skipped ({problem})", flush=True)
            continue
        control, soup = (train(name_, target, entry, args.out, args.steps) for name_ in (algo, "soup"))
        rows.append(dict(entry=name, env=target, control=control, soup=soup))
        print(
            f"{name:60s} {algo}: rc {control['returncode']} ({control['seconds']} s)  soup: rc {soup['returncode']}",
            flush=True,
        )
        if soup["returncode"] and not control["returncode"]:
            print("    " + soup["error"].replace("\n", "\n    "), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(rows, indent=2))
    ran = [row for row in rows if "soup" in row]
    soup_only = [row["entry"] for row in ran if row["soup"]["returncode"] and not row["control"]["returncode"]]
    print(
        f"\n{len(ran)} entries run, {len(rows) - len(ran)} skipped; SOUP fails where the control trains: {soup_only or 'none'}"
    )
    sys.exit(1 if soup_only else 0)


if __name__ == "__main__":
    main()
