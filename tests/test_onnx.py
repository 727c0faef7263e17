"""sb3_soup.export_onnx: the exported graph, run by onnxruntime, acts as model.predict(obs, deterministic=True)."""

import json
import sys

import numpy as np
import pytest
from gymnasium import spaces

pytest.importorskip("onnx")
pytest.importorskip("onnxscript")
ort = pytest.importorskip("onnxruntime")

from image_env import TinyImageEnv  # noqa: E402
from scripts import load_script  # noqa: E402
from test_bad_input import ToyEnv  # noqa: E402  (20-step episodes of random observations)

from sb3_soup import SOUP, export_onnx  # noqa: E402

TINY = dict(net_arch=dict(pi_body=[16], pi_head=[16], qf_body=[16, 16], qf_head=[16]))
SMALL = dict(n_heads=3, learning_starts=20, batch_size=16, buffer_size=500, seed=0, device="cpu", policy_kwargs=TINY)
# every preset, and every confidence strategy ("none" is dbddpg's, "adaptive" soup's)
MODELS = {
    "ddpg": dict(preset="ddpg"),
    "ma_bddpg": dict(preset="ma_bddpg"),
    "multi_ddpg": dict(preset="multi_ddpg"),
    "dbddpg-none": dict(preset="dbddpg"),
    "soup-adaptive": dict(preset="soup"),
    "fixed": dict(confidence="fixed", confidence_kwargs=dict(alpha=0.7)),
    # after 60 steps its diagonal is 0.99**60 = 0.55, not 1 or 1/K
    "decayed": dict(confidence="decayed", confidence_kwargs=dict(decay=0.99)),
    "ucb": dict(confidence="ucb", confidence_kwargs=dict(ucb_lambda=2.0)),  # greedy actions: the mean of the critic heads
}


def session(path) -> "ort.InferenceSession":
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def sample(space: spaces.Space, n: int, seed: int = 1) -> np.ndarray:
    space.seed(seed)
    return np.stack([space.sample() for _ in range(n)])


@pytest.mark.parametrize("name", sorted(MODELS))
def test_onnx_actions_are_predicts(tmp_path, name):
    model = SOUP("MlpPolicy", "Pendulum-v1", **SMALL, **MODELS[name]).learn(60)  # trained a little: the heads differ
    path = export_onnx(model, tmp_path / "policy.onnx")
    graph = session(path)
    assert [node.name for node in graph.get_inputs()] == ["obs"] and [node.name for node in graph.get_outputs()] == ["actions"]
    for batch_size in (1, 16):  # a dynamic batch dimension
        obs = sample(model.observation_space, batch_size)
        (actions,) = graph.run(None, {"obs": obs})
        expected, _ = model.predict(obs, deterministic=True)
        assert actions.shape == expected.shape == (batch_size, 1)
        np.testing.assert_allclose(actions, expected, rtol=0, atol=1e-5)
    if model.policy.n_actor_heads > 1:  # the argmax picks different heads across the batch, as predict does
        view = model.policy.ensemble_view(sample(model.observation_space, 16))
        assert len(set(view.chosen.tolist())) > 1
    if name == "decayed":
        assert 1 / 3 < model.policy.confidence.diagonal < 0.99


def test_onnx_images_with_asymmetric_action_bounds(tmp_path):
    """CnnPolicy: uint8 channel-first images in (scaled to [0, 1] in the graph), actions in [-2, 2] x [0, 1] out."""
    policy_kwargs = dict(TINY, features_extractor_kwargs=dict(features_dim=8))
    model = SOUP("CnnPolicy", TinyImageEnv(), **{**SMALL, "policy_kwargs": policy_kwargs, "batch_size": 8}).learn(40)
    graph = session(export_onnx(model.policy, tmp_path / "cnn.onnx"))  # a policy is exported as its model
    images = sample(model.observation_space, 5)  # (5, 3, 36, 36) uint8, as the policy sees them (transposed by SB3)
    assert images.dtype == np.uint8 and graph.get_inputs()[0].type == "tensor(uint8)"
    (actions,) = graph.run(None, {"obs": images})
    np.testing.assert_allclose(actions, model.predict(images, deterministic=True)[0], rtol=0, atol=1e-5)
    assert (actions[:, 1] >= 0).all() and (actions[:, 1] <= 1).all()


def test_onnx_dict_observations_are_one_input_per_key(tmp_path):
    """Dict observations, one of them float64 (as MuJoCo's): its input is float32, as the policy computes."""
    velocity = spaces.Box(-5, 5, (3,), np.float64)
    observation_space = spaces.Dict({"position": spaces.Box(-1, 1, (2,)), "velocity": velocity})
    model = SOUP("MultiInputPolicy", ToyEnv(observation_space, spaces.Box(-1, 3, (2,))), **SMALL).learn(40)
    graph = session(export_onnx(model, tmp_path / "dict.onnx"))
    inputs = [(node.name, node.type) for node in graph.get_inputs()]
    assert inputs == [("position", "tensor(float)"), ("velocity", "tensor(float)")]
    obs = {key: sample(space, 6) for key, space in observation_space.spaces.items()}
    assert obs["velocity"].dtype == np.float64
    (actions,) = graph.run(None, {key: value.astype(np.float32) for key, value in obs.items()})
    np.testing.assert_allclose(actions, model.predict(obs, deterministic=True)[0], rtol=0, atol=1e-5)


def test_onnx_refuses_what_it_cannot_export(tmp_path, monkeypatch):
    model = SOUP("MlpPolicy", ToyEnv(spaces.Discrete(4), spaces.Box(-1, 1, (1,))), n_heads=2, policy_kwargs=TINY)
    with pytest.raises(ValueError, match=r"takes Box observations or a Dict of Box observations, got Discrete\(4\)"):
        export_onnx(model, tmp_path / "discrete.onnx")
    with pytest.raises(ValueError, match="takes a SOUP model or a SOUPPolicy, got str"):
        export_onnx("model.zip", tmp_path / "str.onnx")
    monkeypatch.setitem(sys.modules, "onnxscript", None)  # as if not installed
    with pytest.raises(ImportError, match=r"pip install 'sb3-soup\[onnx\]'"):
        export_onnx(model, tmp_path / "none.onnx")
    assert not list(tmp_path.iterdir())


def test_latency_benchmark_plumbing(tmp_path):
    """benchmarks/onnx_latency.py --quick: its rows and JSON (not timed: the numbers live in docs/benchmarks.md)."""
    benchmark = load_script("benchmarks/onnx_latency.py")
    result = benchmark.main(["--quick", "--out", str(tmp_path / "quick.json")])
    assert json.loads((tmp_path / "quick.json").read_text()) == json.loads(json.dumps(result))
    assert [row["name"] for row in result["rows"]] == [config["name"] for config in benchmark.QUICK]
    for row in result["rows"]:
        assert row["agree"] and row["calls"] == 10
        assert min(row["predict_ms"], row["torch_ms"], row["onnxruntime_ms"]) > 0
