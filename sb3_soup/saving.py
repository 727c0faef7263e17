"""
SOUP's model zips: what they carry besides SB3's content, and the checks made before loading one.

- **Save format.** Every model zip stores ``_sb3_soup_format`` (:data:`SAVE_FORMAT_VERSION`) and ``_sb3_soup_version``
  (the sb3-soup release that wrote it). A file is read when its format is in
  ``[MIN_READABLE_FORMAT, SAVE_FORMAT_VERSION]`` and refused otherwise, with a message naming both versions.
  Bump :data:`SAVE_FORMAT_VERSION` whenever a change makes older files load wrongly (other parameter names or
  shapes, a renamed attribute), and raise :data:`MIN_READABLE_FORMAT` when older files can no longer be read.
  Format 0 is a file written by sb3-soup 0.1.0a0 before the format was stored: same content, no random-generator state.
  Format 1 (sb3-soup 0.1.0a0) named two attributes differently; :func:`upgrade` renames them.
- **Random generators.** ``SOUP.save`` stores the random generators' states (see
  :func:`sb3_soup.persistence.capture_rng_state`) as ``_rng_state``; ``SOUP.load`` restores them, so that ``load``
  then ``learn(..., reset_num_timesteps=False)`` continues the random streams where ``save`` left them.
"""

import io
import json
import os
import pathlib
import zipfile
from typing import Any

from stable_baselines3.common.save_util import open_path

SAVE_FORMAT_VERSION = 2
"""Format of the model zips this version writes."""

# Attributes renamed since an older format: format -> {old name: new name}
_RENAMED = {2: {"_active_heads": "_active_pairs", "exploration_std": "current_noise_std"}}

MIN_READABLE_FORMAT = 0
"""Oldest format this version reads (0: sb3-soup 0.1.0a0 files written before the format was stored)."""

_ZIP_MAGIC = b"PK\x03\x04"


def package_version() -> str:
    """The installed sb3-soup version (``sb3_soup/version.txt``)."""
    with open(os.path.join(os.path.dirname(__file__), "version.txt")) as file:
        return file.read().strip()


def _name(path: Any) -> str:
    return str(path) if isinstance(path, (str, os.PathLike)) else f"<{type(path).__name__}>"


def read_saved_data(path: str | pathlib.Path | io.BufferedIOBase) -> dict[str, Any]:
    """
    Read the ``data`` entry of a model zip as raw JSON, without unpickling anything, with a clear error for a file
    that is not a model, a truncated or a corrupt one.

    :param path: the model file (``.zip`` may be left out, as with SB3's ``load``) or an open binary file
    :return: the saved attributes; pickled ones are left as SB3 stores them (dicts with ``:serialized:``)
    """
    file = open_path(path, "r", suffix="zip")
    start = file.tell()
    truncated = (
        f"{_name(path)} is a truncated or corrupt model zip ({{error}}): a process killed while saving leaves such files; "
        "load an earlier checkpoint (sb3_soup.checkpoint.latest_checkpoint finds the newest complete one)"
    )
    try:
        head = file.read(64)
        file.seek(start)
        # SB3 writes the 'data' entry first: a zip that starts with it but does not list it was cut short (the
        # zip reader then finds the directory of policy.pth, itself a zip, inside the remains)
        starts_with_data = head[:4] == _ZIP_MAGIC and head[30 : 30 + int.from_bytes(head[26:28], "little")] == b"data"
        try:
            with zipfile.ZipFile(file) as archive:
                if "data" not in archive.namelist():
                    if starts_with_data:
                        raise ValueError(truncated.format(error="its directory has no 'data' entry"))
                    raise ValueError(
                        f"{_name(path)} is a zip archive but not a saved model: it has no 'data' entry "
                        "(SB3's model.save writes data, policy.pth and the optimizers' .pth files)"
                    )
                raw = archive.read("data").decode()
        except zipfile.BadZipFile as error:
            if head[:4] == _ZIP_MAGIC:
                raise ValueError(truncated.format(error=error)) from error
            raise ValueError(
                f"{_name(path)} is not a saved model: it is not a zip archive (model.save writes a .zip; replay buffers "
                "are loaded with model.load_replay_buffer)"
            ) from error
        try:
            data = json.loads(raw)
        except ValueError as error:
            raise ValueError(f"{_name(path)} is a corrupt model zip: its 'data' entry is not valid JSON ({error})") from error
        if not isinstance(data, dict):
            raise ValueError(f"{_name(path)} is not a saved model: its 'data' entry holds {type(data).__name__}, not a dict")
        return data
    finally:
        if isinstance(path, (str, os.PathLike)):
            file.close()
        else:  # leave a caller's file where it was, for SB3's load to read it
            file.seek(start)


def check_saved_format(data: dict[str, Any], path: Any) -> int:
    """
    Refuse a file that SOUP cannot load as saved: not a SOUP model, or a save format this version does not read.

    :param data: from :func:`read_saved_data`
    :param path: the file, for the messages
    :return: the file's save format
    """
    saved_format = data.get("_sb3_soup_format")
    if saved_format is None:
        if "n_actor_heads" not in data or "n_critic_heads" not in data:
            policy = data.get("policy_class")
            module = policy.get("__module__", "?") if isinstance(policy, dict) else "?"
            raise ValueError(
                f"{_name(path)} was not saved by SOUP (its policy class comes from {module}): load it with the algorithm "
                "that saved it (e.g. stable_baselines3.TD3.load)"
            )
        saved_format = 0  # sb3-soup 0.1.0a0, before the format was stored
    saved_version = data.get("_sb3_soup_version", "0.1.0a0")
    if not isinstance(saved_format, int) or saved_format > SAVE_FORMAT_VERSION:
        raise ValueError(
            f"{_name(path)} was saved by sb3-soup {saved_version} in save format {saved_format!r}; this sb3-soup "
            f"{package_version()} reads formats {MIN_READABLE_FORMAT} to {SAVE_FORMAT_VERSION}: upgrade sb3-soup "
            f"(pip install -U sb3-soup) to load it"
        )
    if saved_format < MIN_READABLE_FORMAT:
        raise ValueError(
            f"{_name(path)} was saved by sb3-soup {saved_version} in save format {saved_format}, which this sb3-soup "
            f"{package_version()} no longer reads (formats {MIN_READABLE_FORMAT} to {SAVE_FORMAT_VERSION}): load it with "
            f"sb3-soup {saved_version} (pip install sb3-soup=={saved_version}) and retrain, or keep using that version"
        )
    return saved_format


def upgrade(model: Any, saved_format: int) -> None:
    """
    Bring a model loaded from an older save format to this version's attribute names (e.g. the active head pairs of
    a checkpoint, so that resuming it stays exact).

    :param model: the loaded model
    :param saved_format: its file's format
    """
    for new_format, renamed in sorted(_RENAMED.items()):
        if saved_format >= new_format:
            continue
        for old, new in renamed.items():
            if old in vars(model):
                setattr(model, new, vars(model).pop(old))
