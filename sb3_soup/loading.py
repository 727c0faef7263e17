"""
Loading SOUP's files: the save format's version check, and SB3's ``load``, ``set_parameters`` and
``load_replay_buffer`` with the checks that turn a file that does not fit into a clear error (:class:`CheckedLoading`).
SOUP saves through SB3's two hooks (``SOUP._excluded_save_params``, ``SOUP._get_torch_save_params``).
"""

import io
import pathlib
from typing import Any, TypeVar

import torch as th
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import GymEnv
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

from sb3_soup.arguments import check_arguments
from sb3_soup.buffers import load_bootstrapped_buffer
from sb3_soup.checkpoint import read_model_data
from sb3_soup.policies import SOUPPolicy

SelfCheckedLoading = TypeVar("SelfCheckedLoading", bound="CheckedLoading")

__version__ = pathlib.Path(__file__).with_name("version.txt").read_text().strip()
SAVE_FORMAT_VERSION = 3
"""Format of the model zips this version writes and reads: bump it when a change makes older files load wrongly (other
parameter names or shapes, a renamed attribute); ``SOUP.load`` refuses the other formats, naming both versions."""

STRUCTURAL_ARGUMENTS = ("n_heads", "n_actor_heads", "n_critic_heads", "preset", "confidence", "confidence_kwargs", "policy")
"""SOUP's arguments a saved model fixes (its networks and its strategy are built from them): ``SOUP.load`` refuses them."""


def check_save_format(data: dict[str, Any], path: Any) -> None:
    """
    Refuse a file that is not a SOUP model in this version's save format
    (:data:`sb3_soup.loading.SAVE_FORMAT_VERSION`), saying which versions and what to do: the version check of
    sb3-soup's model files.

    :param data: the file's ``data`` (:func:`sb3_soup.checkpoint.read_model_data`)
    :param path: the file, for the message
    """
    saved_format = data.get("_sb3_soup_format", 0)  # 0: sb3-soup 0.1.0a0 before the format was stored
    if saved_format == 0 and not {"n_actor_heads", "n_critic_heads"} <= data.keys():
        policy = data.get("policy_class")
        module = policy.get("__module__", "?") if isinstance(policy, dict) else "?"
        raise ValueError(
            f"{path} was not saved by SOUP (its policy class comes from {module}): load it with the algorithm that saved "
            "it (e.g. stable_baselines3.TD3.load)"
        )
    if saved_format == SAVE_FORMAT_VERSION:
        return
    saved_version = data.get("_sb3_soup_version", "0.1.0a0")
    if isinstance(saved_format, int) and saved_format > SAVE_FORMAT_VERSION:
        advice = "upgrade sb3-soup (pip install -U sb3-soup) to load it"
    elif saved_version == __version__:  # a development version, before its save format changed
        advice = "it was saved during this version's development, before its format changed: train a new model"
    else:
        advice = f"load it with sb3-soup {saved_version} (pip install sb3-soup=={saved_version}), or train a new model"
    raise ValueError(
        f"{path} was saved by sb3-soup {saved_version} in save format {saved_format!r}; this sb3-soup {__version__} reads "
        f"save format {SAVE_FORMAT_VERSION} only: {advice}"
    )


def check_loadable(data: dict[str, Any], path: Any, kwargs: dict[str, Any]) -> None:
    """
    Refuse what ``SOUP.load`` cannot do: a file in another save format (:func:`sb3_soup.loading.check_save_format`), or keyword
    arguments that would change what the saved model fixes (:data:`sb3_soup.loading.STRUCTURAL_ARGUMENTS`).

    :param data: the file's ``data`` (:func:`sb3_soup.checkpoint.read_model_data`)
    :param path: the file, for the messages
    :param kwargs: the settings ``SOUP.load`` was asked to change
    """
    check_save_format(data, path)
    fixed = sorted(set(kwargs) & set(STRUCTURAL_ARGUMENTS))
    if fixed:
        saved = ", ".join(f"{key}={data.get(key)!r}" for key in fixed if ":serialized:" not in str(data.get(key)))
        raise ValueError(
            f"{fixed} cannot be changed when loading: the saved model was built with {saved or 'other objects'}; "
            "create a new SOUP to use other values"
        )


class NetworksMismatchError(RuntimeError):
    """
    Saved parameters that do not fit a model's networks (``set_parameters``, ``SOUP.load``). A ``RuntimeError``, as
    torch's ``load_state_dict`` raises there, and so SB3's ``set_parameters`` for TD3 and DDPG; not a ``ValueError``,
    which SB3's ``load`` takes for its patch of old DQN files and replaces by ``KeyError: 'policy.optimizer'``.
    """


class CheckedLoading(OffPolicyAlgorithm):
    """SB3's loading of an off-policy algorithm, with the checks of SOUP's files (SOUP's base class)."""

    policy: SOUPPolicy

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfCheckedLoading],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfCheckedLoading:
        """
        SB3's ``load`` (see there for the parameters), once the file is checked to be a SOUP model in this version's
        save format (:func:`sb3_soup.loading.check_loadable`). ``kwargs`` may change settings (e.g.
        ``learning_starts``), not those that shape the networks or the strategy (head counts, preset, confidence): the
        file's.
        """
        check_loadable(read_model_data(path), path, kwargs)
        model = super().load(path, env, device, custom_objects, print_system_info, force_reset, **check_arguments(**kwargs))
        model._sb3_soup_version = __version__  # type: ignore[attr-defined]  # from now on this version's model
        return model

    def set_parameters(
        self, load_path_or_dict: str | dict[str, Any], exact_match: bool = True, device: th.device | str = "auto"
    ) -> None:
        """
        SB3's ``set_parameters``, saying what to do when the saved networks have other shapes (``SOUP.load``, without
        a ``custom_objects`` that changes ``policy_kwargs``).

        :raises NetworksMismatchError: the saved parameters have other shapes than this model's
        """
        try:
            super().set_parameters(load_path_or_dict, exact_match, device)
        except RuntimeError as error:
            mismatches = [line.strip() for line in str(error).splitlines() if "size mismatch" in line]
            if not mismatches:
                raise
            raise NetworksMismatchError(
                f"the saved parameters do not fit this model's networks (other head counts or net_arch?): {mismatches[0]} "
                f"({len(mismatches)} mismatches). SOUP.load builds a model as it was saved, unless custom_objects gives "
                "other policy_kwargs"
            ) from error

    def load_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """
        SB3's ``load_replay_buffer``, once the file is checked to fit this model (bootstrap masks for each head pair,
        as many envs; :func:`sb3_soup.buffers.load_bootstrapped_buffer`): the model's buffer is only replaced then.

        :param path: Path to the pickled replay buffer
        :param truncate_last_traj: When using ``HerReplayBuffer``: if ``True``, we assume that the last trajectory in the
            replay buffer was finished (and truncate it); if ``False``, we assume that we continue the same trajectory
            (same episode), as SB3
        """
        buffer = load_bootstrapped_buffer(path, self.policy.n_pairs, self.n_envs, self.verbose)
        if isinstance(buffer, HerReplayBuffer):
            if self.env is None:
                raise ValueError(
                    f"the replay buffer in {path} is a HerReplayBuffer, which needs the model's env (to compute the "
                    "rewards of relabelled goals): set it first (SOUP.load(path, env=...) or model.set_env(env))"
                )
            buffer.set_env(self.env)
            if truncate_last_traj:
                buffer.truncate_last_trajectory()
        buffer.device = self.device
        self.replay_buffer = buffer
