"""The README's main job (`make demo`) on a tiny budget: model, learning curve and evaluation returns come out."""

import json

import numpy as np

from sb3_soup import SOUP
from sb3_soup.demo import main


def test_demo_writes_model_plot_and_returns(tmp_path, capsys):
    summary = main(["--timesteps", "400", "--eval-freq", "200", "--eval-episodes", "1", "--n-heads", "3",
                    "--out", str(tmp_path), "--no-progress-bar"])  # fmt: skip
    printed = capsys.readouterr().out
    assert "Evaluation returns" in printed and "step     400" in printed and "Final evaluation" in printed
    assert (tmp_path / "learning_curve.png").stat().st_size > 10_000
    assert json.loads((tmp_path / "summary.json").read_text())["final_mean_return"] == summary["final_mean_return"]
    assert np.load(tmp_path / "evaluations.npz")["timesteps"].tolist() == [200, 400]
    model = SOUP.load(tmp_path / "soup_model.zip")
    assert model.n_heads == 3 and model.num_timesteps == 400
