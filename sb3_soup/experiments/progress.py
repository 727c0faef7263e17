"""Progress bars for a grid: one overall bar plus one per run, fed by the runs' ``status.json`` files."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from sb3_soup.experiments.runner import STATUS_FILE, read_json


class ProgressBoard:
    """
    Polls the runs' status files and draws the bars. Works for any backend whose workers write to a folder this
    process can read (local processes, or Ray on a shared filesystem).

    :param specs: the runs (:class:`~sb3_soup.experiments.grid.RunSpec`)
    :param enabled: draw bars (``False``: stay silent, e.g. in tests or logs)
    """

    def __init__(self, specs: Sequence[Any], enabled: bool = True) -> None:
        self.specs = list(specs)
        self.enabled = enabled
        self.steps = {spec.key: 0 for spec in self.specs}
        self.bars: dict[str, Any] = {}
        if not enabled:
            return
        total = sum(spec.timesteps for spec in self.specs)
        self.overall = tqdm(total=total, desc=f"all {len(self.specs)} runs", unit="step", position=0, dynamic_ncols=True)
        width = max((len(spec.key) for spec in self.specs), default=10)
        for position, spec in enumerate(self.specs, start=1):
            self.bars[spec.key] = tqdm(
                total=spec.timesteps,
                desc=spec.key.ljust(width),
                unit="step",
                position=position,
                leave=True,
                dynamic_ncols=True,
            )

    def poll(self) -> None:
        """Read every run's status file and move the bars."""
        for spec in self.specs:
            status = read_json(Path(spec.run_dir) / STATUS_FILE)
            if status is not None:
                self.update(spec.key, int(status.get("step", 0)), str(status.get("status", "")))

    def update(self, key: str, step: int, status: str = "") -> None:
        """
        :param key: the run's key
        :param step: its steps done
        :param status: its status, shown next to the bar
        """
        previous = self.steps.get(key, 0)
        self.steps[key] = step
        if not self.enabled:
            return
        bar = self.bars[key]
        bar.n = step
        if status:
            bar.set_postfix_str(status, refresh=False)
        bar.refresh()
        self.overall.n = sum(self.steps.values())
        if step != previous:
            self.overall.refresh()

    def close(self) -> None:
        """Close the bars."""
        if self.enabled:
            for bar in self.bars.values():
                bar.close()
            self.overall.close()
