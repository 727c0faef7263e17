"""
Progress of a grid, fed by the runs' ``status.json`` files: in a terminal, one overall bar plus one bar per run
(tqdm's public API: a run's bar starts at the step it resumes from, and its clock when it starts running);
elsewhere (a log file, a pipe, CI), plain lines: one when a run ends and a summary of the running ones now and then.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

from tqdm.auto import tqdm

from sb3_soup.checkpoint import find_checkpoints
from sb3_soup.experiments.runner import CHECKPOINT_DIR, STATUS_FILE, read_json

#: Seconds between two summary lines in line mode.
LINE_INTERVAL_S = 300.0


def progress_mode(enabled: bool, stream: TextIO | None = None) -> str:
    """
    :param enabled: whether the user wants progress shown (``--no-progress`` turns it off)
    :param stream: where it goes (default: standard error)
    :return: ``"bars"`` when ``stream`` is a terminal, ``"lines"`` when it is not, ``"off"`` when not enabled
    """
    if not enabled:
        return "off"
    stream = stream if stream is not None else sys.stderr
    return "bars" if stream.isatty() else "lines"


class ProgressBoard:
    """
    Polls the runs' status files and shows how far they are. Works for any backend whose workers write to a folder
    this process can read (local processes, or Ray on a shared filesystem).

    :param specs: the runs (:class:`~sb3_soup.experiments.grid.RunSpec`)
    :param mode: ``"bars"`` (tqdm bars), ``"lines"`` (plain lines) or ``"off"`` (silent)
    :param stream: where to write (default: standard error)
    :param line_interval: seconds between summary lines in ``"lines"`` mode
    """

    def __init__(
        self, specs: Sequence[Any], mode: str = "bars", stream: TextIO | None = None, line_interval: float = LINE_INTERVAL_S
    ) -> None:
        if mode not in ("bars", "lines", "off"):
            raise ValueError(f"mode must be 'bars', 'lines' or 'off', got {mode!r}")
        self.specs = list(specs)
        # a run's name: model/seed_N, with its env when the runs are on several (screen run)
        self._several_envs = len({spec.env_id for spec in self.specs}) > 1
        self.mode = mode
        self.stream = stream if stream is not None else sys.stderr
        self.line_interval = line_interval
        self.steps = {self.name(spec): _resume_step(spec) for spec in self.specs}
        self.totals = {self.name(spec): spec.timesteps for spec in self.specs}
        self.status = {self.name(spec): "pending" for spec in self.specs}
        self.ended: dict[str, dict[str, Any]] = {}
        self.started = self.last_line = time.monotonic()
        self.bars: dict[str, Any] = {}
        self.seen: set[str] = set()
        if mode != "bars":
            return
        total = sum(spec.timesteps for spec in self.specs)
        common = dict(unit="step", unit_scale=True, dynamic_ncols=True, file=self.stream, leave=True)
        self.overall = tqdm(
            total=total, initial=sum(self.steps.values()), desc=f"all {len(self.specs)} runs", position=0, **common
        )
        width = max((len(self.name(spec)) for spec in self.specs), default=10)
        for position, spec in enumerate(self.specs, start=1):
            bar = tqdm(
                total=spec.timesteps,
                initial=self.steps[self.name(spec)],
                desc=self.name(spec).ljust(width),
                position=position,
                **common,
            )
            bar.set_postfix_str("pending")
            self.bars[self.name(spec)] = bar

    def name(self, spec: Any) -> str:
        """:return: the name a run is shown and finished by: ``model/seed_N``, ``env_id/model/seed_N`` on several envs"""
        return spec.run_id if self._several_envs else spec.key

    @property
    def enabled(self) -> bool:
        """Whether bars are drawn."""
        return self.mode == "bars"

    def poll(self) -> None:
        """Read every unfinished run's status file and move the bars (or write a summary line when it is time)."""
        for spec in self.specs:
            if self.name(spec) in self.ended:
                continue
            status = read_json(Path(spec.run_dir) / STATUS_FILE)
            if status is not None and status.get("status") == "running":
                self.update(self.name(spec), int(status.get("step", 0)), "running")
        if self.mode == "lines" and time.monotonic() - self.last_line >= self.line_interval:
            self.write_summary()

    def update(self, key: str, step: int, status: str = "") -> None:
        """
        :param key: the run's key
        :param step: its steps done
        :param status: its status, shown next to the bar
        """
        delta = step - self.steps[key]
        self.steps[key] = step
        if status:
            self.status[key] = status
        if self.mode != "bars":
            return
        bar = self.bars[key]
        if status == "running" and key not in self.seen:
            # The run starts (or resumes) now: its time, rate and ETA count from here, not from the grid's start.
            self.seen.add(key)
            bar.unpause()
        bar.update(delta)
        if status:
            bar.set_postfix_str(status, refresh=False)
        bar.refresh()
        self.overall.update(delta)
        self.overall.set_postfix_str(self._counts(), refresh=False)
        self.overall.refresh()

    def finish(self, key: str, result: dict[str, Any]) -> None:
        """
        A run ended: show its outcome (in line mode, one line).

        :param key: the run's key
        :param result: its result (see :func:`~sb3_soup.experiments.runner.run_one`)
        """
        self.ended[key] = result
        status = str(result["status"])
        step = int(result.get("step") or 0)
        # A finished (or skipped) run counts in full; others count the steps they reached.
        self.update(key, self.totals[key] if status in ("finished", "skipped") else step, status)
        if self.mode == "lines":
            detail = f": {result['error']}" if result.get("error") else ""
            self._write(f"[{len(self.ended)}/{len(self.specs)}] {key}: {status} at step {step}{detail}")

    def write_summary(self) -> None:
        """One line: counts, then each running run's progress."""
        self.last_line = time.monotonic()
        running = [
            f"{key} {self.steps[key]}/{self.totals[key]}"
            for key, status in self.status.items()
            if status == "running" and key not in self.ended
        ]
        elapsed = time.monotonic() - self.started
        self._write(f"[{elapsed / 60:.0f} min] {self._counts()}" + (f"; running: {', '.join(running)}" if running else ""))

    def _counts(self) -> str:
        ended = [result["status"] for result in self.ended.values()]
        running = sum(status == "running" and key not in self.ended for key, status in self.status.items())
        parts = [f"{len(ended)}/{len(self.specs)} ended", f"{running} running"]
        parts += [f"{ended.count(status)} {status}" for status in ("failed", "busy", "interrupted") if status in ended]
        return ", ".join(parts)

    def _write(self, line: str) -> None:
        print(line, file=self.stream, flush=True)

    def close(self) -> None:
        """Close the bars (the overall one first: it stays on top)."""
        if self.mode == "bars":
            self.overall.close()
            for bar in self.bars.values():
                bar.close()


def _resume_step(spec: Any) -> int:
    """The step a run starts from: its newest checkpoint's, 0 without one."""
    checkpoints = find_checkpoints(Path(spec.run_dir) / CHECKPOINT_DIR)
    return checkpoints[0].step if checkpoints else 0
