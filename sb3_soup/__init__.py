"""sb3-soup: SOUP (Self-Adaptive Double Bootstrapped DDPG, Zheng et al., IJCAI 2018) for Stable-Baselines3."""

from sb3_soup.buffers import (
    BootstrappedDictReplayBuffer,
    BootstrappedHerReplayBuffer,
    BootstrappedNStepReplayBuffer,
    BootstrappedReplayBuffer,
)
from sb3_soup.confidence import (
    AdaptiveConfidence,
    ConfidenceStep,
    ConfidenceStrategy,
    DecayedConfidence,
    FixedConfidence,
    LCBConfidence,
    NoConfidence,
    UCBConfidence,
)
from sb3_soup.export import export_onnx
from sb3_soup.loading import __version__  # read from version.txt, as saved models record it
from sb3_soup.noise import DecayingNormalActionNoise
from sb3_soup.policies import CnnPolicy, EnsembleView, MlpPolicy, MultiInputPolicy, ObservationSpaceError, SOUPPolicy
from sb3_soup.presets import PRESETS, paper_settings
from sb3_soup.soup import SOUP

__all__ = [
    "PRESETS",
    "SOUP",
    "AdaptiveConfidence",
    "BootstrappedDictReplayBuffer",
    "BootstrappedHerReplayBuffer",
    "BootstrappedNStepReplayBuffer",
    "BootstrappedReplayBuffer",
    "CnnPolicy",
    "ConfidenceStep",
    "ConfidenceStrategy",
    "DecayedConfidence",
    "DecayingNormalActionNoise",
    "EnsembleView",
    "FixedConfidence",
    "LCBConfidence",
    "MlpPolicy",
    "MultiInputPolicy",
    "NoConfidence",
    "ObservationSpaceError",
    "SOUPPolicy",
    "UCBConfidence",
    "__version__",
    "export_onnx",
    "paper_settings",
]
