"""Lightning training of torchhys models: module, data, CLI and the paper reproduction."""

from training.data import HysteresisDataModule
from training.module import InverseHysteresisModule

__all__ = ["HysteresisDataModule", "InverseHysteresisModule"]
