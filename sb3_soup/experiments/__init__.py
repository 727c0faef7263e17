"""
Reproduce the SOUP paper's comparisons: run a suite of (model, seed) runs in parallel, resumably, then report
Table 1's metrics and Figures 4-7. See ``python -m sb3_soup.experiments --help`` and ``docs/results.md``.
"""

from sb3_soup.experiments.grid import SUITES, VARIANTS, RunSpec, build_grid
from sb3_soup.experiments.metrics import model_metrics
from sb3_soup.experiments.report import make_report

__all__ = ["SUITES", "VARIANTS", "RunSpec", "build_grid", "make_report", "model_metrics"]
