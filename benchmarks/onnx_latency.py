"""
Latency of SOUP's deterministic E-action policy exported to ONNX (``sb3_soup.export_onnx``) run by onnxruntime, against
``model.predict(obs, deterministic=True)`` and against the same PyTorch graph called directly.

Per configuration and batch size, three ways to act on a batch of observations (NumPy in, NumPy out):

- ``predict``: ``model.predict(obs, deterministic=True)`` (SB3's checks and conversions, ``torch.no_grad``);
- ``torch``: the exported module (``OnnxableSOUPPolicy``) called on a tensor under ``torch.inference_mode``, the
  PyTorch cost of the graph alone;
- ``onnxruntime``: ``InferenceSession.run`` on the exported file (CPU execution provider).

One thread each (``torch.set_num_threads(1)``, onnxruntime ``intra_op_num_threads=1``, ``inter_op_num_threads=1``).
The three are interleaved: each repeat times ``--calls`` calls of each in turn, so that a change of machine load hits
them alike; the table gives the median over all calls and the ratio to ``predict``.

Usage::

    python benchmarks/onnx_latency.py --out onnx_latency.json          # the table of docs/benchmarks.md (~2 minutes)
    python benchmarks/onnx_latency.py --quick --out quick.json         # two small rows (a smoke test)
"""

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

# Hopper-v4 (11-dimensional observations, 3-dimensional actions), the paper's sizes; one image row at Atari's size
CONFIGS: list[dict[str, Any]] = [
    dict(name="hopper ddpg (K=1)", env="Hopper-v4", preset="ddpg", n_heads=1, batch_sizes=[1, 8, 256]),
    dict(name="hopper dbddpg K=5 none", env="Hopper-v4", preset="dbddpg", n_heads=5, batch_sizes=[1, 8, 256]),
    dict(name="hopper soup K=5 adaptive", env="Hopper-v4", preset="soup", n_heads=5, batch_sizes=[1, 8, 256]),
    dict(name="hopper soup K=10 adaptive", env="Hopper-v4", preset="soup", n_heads=10, batch_sizes=[1, 8, 256]),
    dict(name="images 84x84 soup K=5 adaptive", env="images", preset="soup", n_heads=5, batch_sizes=[1, 8]),
]
QUICK: list[dict[str, Any]] = [
    dict(name="pendulum soup K=2 adaptive", env="Pendulum-v1", preset="soup", n_heads=2, batch_sizes=[1]),
    dict(name="pendulum ddpg (K=1)", env="Pendulum-v1", preset="ddpg", n_heads=1, batch_sizes=[1]),
]


def _single_thread() -> None:
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = "1"


def make_env(name: str) -> Any:
    """:return: the env of a configuration (``"images"``: uint8 (3, 84, 84) images and 3-dimensional actions)"""
    import gymnasium as gym
    import numpy as np
    from gymnasium import spaces

    if name != "images":
        return name

    class Images(gym.Env):
        observation_space = spaces.Box(0, 255, (3, 84, 84), np.uint8)
        action_space = spaces.Box(-1, 1, (3,), np.float32)

        def reset(self, seed=None, options=None):  # type: ignore[no-untyped-def]
            super().reset(seed=seed)
            return self.observation_space.sample(), {}

        def step(self, action):  # type: ignore[no-untyped-def]
            return self.observation_space.sample(), 0.0, False, False, {}

    return Images()


def time_calls(function: Any, calls: int) -> list[float]:
    """:return: the duration of each of ``calls`` calls of ``function``, in ms"""
    durations = []
    for _ in range(calls):
        start = time.perf_counter()
        function()
        durations.append((time.perf_counter() - start) * 1e3)
    return durations


def measure(config: dict[str, Any], repeats: int, calls: int, folder: Path) -> list[dict[str, Any]]:
    """:return: one row per batch size of the configuration: median ms of predict, torch and onnxruntime"""
    import numpy as np
    import onnxruntime as ort
    import torch as th

    from sb3_soup import SOUP, export_onnx
    from sb3_soup.export import OnnxableSOUPPolicy

    policy = "CnnPolicy" if config["env"] == "images" else "MlpPolicy"
    kwargs = dict(preset=config["preset"], n_heads=config["n_heads"], buffer_size=1000, seed=0, device="cpu")
    model = SOUP(policy, make_env(config["env"]), **kwargs)
    path = export_onnx(model, folder / "policy.onnx")
    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    graph = OnnxableSOUPPolicy(model.policy).eval()
    (input_dtype,) = graph.input_dtypes()
    rows = []
    for batch_size in config["batch_sizes"]:
        model.observation_space.seed(0)
        obs = np.stack([model.observation_space.sample() for _ in range(batch_size)])

        def predict(obs: np.ndarray = obs) -> Any:
            return model.predict(obs, deterministic=True)[0]

        def torch_graph(obs: np.ndarray = obs) -> Any:
            with th.inference_mode():
                return graph(th.as_tensor(obs)).numpy()

        def onnxruntime(obs: np.ndarray = obs) -> Any:
            return session.run(None, {"obs": np.asarray(obs, dtype=input_dtype)})[0]  # float64 (MuJoCo) -> float32

        ways = {"predict": predict, "torch": torch_graph, "onnxruntime": onnxruntime}
        outputs = {name: way() for name, way in ways.items()}  # warm-up, and the three agree
        agree = all(np.allclose(output, outputs["predict"], atol=1e-5) for output in outputs.values())
        durations: dict[str, list[float]] = {name: [] for name in ways}
        for repeat in range(repeats):
            names = list(ways)[repeat % len(ways) :] + list(ways)[: repeat % len(ways)]  # rotated order
            for name in names:
                durations[name] += time_calls(ways[name], calls)
        medians = {name: statistics.median(values) for name, values in durations.items()}
        rows.append(
            dict(
                name=config["name"],
                batch_size=batch_size,
                agree=agree,
                predict_ms=medians["predict"],
                torch_ms=medians["torch"],
                onnxruntime_ms=medians["onnxruntime"],
                onnxruntime_x_predict=medians["onnxruntime"] / medians["predict"],
                onnxruntime_x_torch=medians["onnxruntime"] / medians["torch"],
                onnx_file_kb=path.stat().st_size / 1024,
                calls=len(durations["predict"]),
            )
        )
        print(
            f"{config['name']:32s} B={batch_size:<4d} predict {medians['predict']:7.3f} ms  torch {medians['torch']:7.3f} ms"
            f"  onnxruntime {medians['onnxruntime']:7.3f} ms ({medians['onnxruntime'] / medians['predict']:.2f}x predict)"
            + ("" if agree else "  ACTIONS DIFFER"),
            flush=True,
        )
    return rows


def machine() -> dict[str, Any]:
    import onnxruntime as ort
    import torch as th

    return dict(
        date=time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        platform=platform.platform(),
        processor=platform.processor(),
        cpus=os.cpu_count(),
        load_average=os.getloadavg(),
        torch=th.__version__,
        onnxruntime=ort.__version__,
    )


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument("--out", help="JSON file to write")
    parser.add_argument("--quick", action="store_true", help="two small Pendulum rows, few calls (a smoke test)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--calls", type=int, default=200, help="calls of each way per repeat")
    args = parser.parse_args(argv)
    _single_thread()
    import torch as th

    th.set_num_threads(1)
    configs, repeats, calls = (QUICK, 2, 5) if args.quick else (CONFIGS, args.repeats, args.calls)
    start = time.time()
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for config in configs:
            rows += measure(config, repeats, calls, Path(folder))
    result = dict(machine=machine(), repeats=repeats, calls=calls, seconds=time.time() - start, rows=rows)
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
