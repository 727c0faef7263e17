"""
A run's logs: the Monitor CSV (one row per training episode), SB3's CSV logger (``progress.csv``) and the
deterministic evaluations (``evaluations.csv``, one row per evaluation episode), all kept continuous across resumes:
rows written after the step of the checkpoint a run resumes from are cut, then new rows are appended.
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import gymnasium as gym
import pandas as pd
from stable_baselines3.common.logger import CSVOutputFormat, Logger
from stable_baselines3.common.monitor import Monitor

from sb3_soup.checkpoint import atomic_write

MONITOR_FILE = "monitor.csv"
PROGRESS_FILE = "progress.csv"
EVALUATIONS_FILE = "evaluations.csv"
EVALUATION_COLUMNS = ("step", "episode", "return", "length")
STEP_KEY = "time/total_timesteps"
_MONITOR_HEADER_LINES = 2  # '#{json}' then 'r,l,t'


def monitor_env(env: gym.Env, run_dir: str | os.PathLike) -> Monitor:
    """
    Wrap ``env`` in a Monitor writing ``run_dir/monitor.csv``, appending to the file when it exists.

    :param env: the environment
    :param run_dir: the run's folder
    :return: the wrapped environment
    """
    path = Path(run_dir) / MONITOR_FILE
    return Monitor(env, str(path), override_existing=not path.is_file())


def count_episodes(run_dir: str | os.PathLike) -> int:
    """
    :param run_dir: the run's folder
    :return: the number of episodes in its Monitor CSV
    """
    path = Path(run_dir) / MONITOR_FILE
    if not path.is_file():
        return 0
    with open(path) as stream:
        return max(0, sum(1 for line in stream if line.strip()) - _MONITOR_HEADER_LINES)


def truncate_monitor(run_dir: str | os.PathLike, max_step: int) -> None:
    """
    Keep the episodes of the run's Monitor CSV that ended by step ``max_step`` (the header stays). A run trains on one
    env, so an episode ends at the sum of the episode lengths so far; a last line cut short by a kill is dropped.

    :param run_dir: the run's folder
    :param max_step: the last step to keep (the checkpoint's ``num_timesteps``)
    """
    path = Path(run_dir) / MONITOR_FILE
    lines = [line for line in path.read_text().splitlines(keepends=True) if line.strip()] if path.is_file() else []
    if len(lines) < _MONITOR_HEADER_LINES:
        return
    header, rows = lines[:_MONITOR_HEADER_LINES], lines[_MONITOR_HEADER_LINES:]
    length = next(csv.reader([header[-1]])).index("l")
    kept, end = [], 0
    for line in rows:
        if not line.endswith("\n"):
            break
        end += int(next(csv.reader([line]))[length])
        if end > max_step:
            break
        kept.append(line)
    text = "".join(header + kept)
    atomic_write(path, lambda tmp: tmp.write_text(text))


def truncate_progress(run_dir: str | os.PathLike, max_step: int) -> None:
    """
    Drop the rows of the run's ``progress.csv`` logged after step ``max_step``.

    :param run_dir: the run's folder
    :param max_step: the last step to keep (the checkpoint's ``num_timesteps``)
    """
    _truncate_csv(Path(run_dir) / PROGRESS_FILE, STEP_KEY, max_step)


def truncate_evaluations(run_dir: str | os.PathLike, max_step: int) -> None:
    """
    Drop the rows of the run's ``evaluations.csv`` written after step ``max_step``.

    :param run_dir: the run's folder
    :param max_step: the last step to keep (the checkpoint's ``num_timesteps``)
    """
    _truncate_csv(Path(run_dir) / EVALUATIONS_FILE, "step", max_step)


def append_evaluation(run_dir: str | os.PathLike, step: int, returns: list[float], lengths: list[int]) -> None:
    """
    Append one evaluation (its episodes) to the run's ``evaluations.csv``.

    :param run_dir: the run's folder
    :param step: the training step it was made at
    :param returns: the return of each episode
    :param lengths: the length of each episode
    """
    path = Path(run_dir) / EVALUATIONS_FILE
    new = not path.is_file() or path.stat().st_size == 0
    with open(path, "a", newline="") as stream:
        writer = csv.writer(stream, lineterminator="\n")
        if new:
            writer.writerow(EVALUATION_COLUMNS)
        writer.writerows((int(step), episode, float(r), int(n)) for episode, (r, n) in enumerate(zip(returns, lengths)))


def read_evaluations(run_dir: str | os.PathLike) -> pd.DataFrame:
    """
    :param run_dir: the run's folder
    :return: its evaluation episodes (columns ``step``, ``episode``, ``return``, ``length``); empty when there are none
    """
    path = Path(run_dir) / EVALUATIONS_FILE
    if not path.is_file() or path.stat().st_size == 0:
        return pd.DataFrame({name: pd.Series(dtype=float) for name in EVALUATION_COLUMNS})
    return pd.read_csv(path)


def _truncate_csv(path: Path, step_column: str, max_step: int) -> None:
    """Drop the rows of a CSV file whose ``step_column`` is greater than ``max_step`` (rows without a step stay)."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    with open(path, newline="") as stream:
        rows = list(csv.reader(stream))
    header, body = rows[0], rows[1:]
    if step_column in header:
        column = header.index(step_column)
        body = [row for row in body if row[column] == "" or float(row[column]) <= max_step]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(body)
    atomic_write(path, lambda tmp: tmp.write_text(buffer.getvalue()))


class AppendingCSVOutputFormat(CSVOutputFormat):
    """
    SB3's CSV output, continuing an existing file (its header gives the known columns) instead of truncating it.

    :param filename: the CSV file
    """

    def __init__(self, filename: str) -> None:
        path = Path(filename)
        if not path.is_file() or path.stat().st_size == 0:
            super().__init__(filename)
            return
        self.file = open(path, "r+")
        header = self.file.readline().rstrip("\n")
        self.keys = next(csv.reader([header])) if header else []
        self.separator = ","
        self.quotechar = '"'
        self.file.seek(0, os.SEEK_END)


def make_logger(run_dir: str | os.PathLike) -> Logger:
    """
    :param run_dir: the run's folder
    :return: an SB3 logger writing (appending to) ``run_dir/progress.csv``
    """
    Path(run_dir).mkdir(parents=True, exist_ok=True)
    return Logger(folder=str(run_dir), output_formats=[AppendingCSVOutputFormat(str(Path(run_dir) / PROGRESS_FILE))])


def read_monitor(run_dir: str | os.PathLike) -> pd.DataFrame:
    """
    :param run_dir: the run's folder
    :return: its episodes (columns ``r`` return, ``l`` length, ``t`` seconds); empty when there are none
    """
    path = Path(run_dir) / MONITOR_FILE
    if not path.is_file() or count_episodes(run_dir) == 0:
        return pd.DataFrame({"r": pd.Series(dtype=float), "l": pd.Series(dtype=int), "t": pd.Series(dtype=float)})
    return pd.read_csv(path, skiprows=1)


def read_progress(run_dir: str | os.PathLike) -> pd.DataFrame:
    """
    :param run_dir: the run's folder
    :return: its logger rows (SB3 keys as columns); empty when there are none
    """
    path = Path(run_dir) / PROGRESS_FILE
    if not path.is_file() or path.stat().st_size == 0:
        return pd.DataFrame()
    return pd.read_csv(path)
