"""Lightning training of torchhys models: module, data, CLI and the paper reproduction."""

from torchhys.training.data import HysteresisDataModule
from torchhys.training.module import InverseHysteresisModule

__all__ = ["HysteresisDataModule", "InverseHysteresisModule"]
