"""Lightning training of torchhys models: the module and the datamodule (the command line is
:mod:`torchhys.cli`, the data reading :mod:`torchhys.data`, the paper reproduction
:mod:`torchhys.reproduce`)."""

from torchhys.training.data import HysteresisDataModule
from torchhys.training.module import InverseHysteresisModule

__all__ = ["HysteresisDataModule", "InverseHysteresisModule"]
