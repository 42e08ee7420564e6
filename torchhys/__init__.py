"""torchhys: differentiable hysteresis and inverse-hysteresis modelling in PyTorch.

The functional core lives in :mod:`torchhys.functional`; the ``nn.Module`` wrappers
that hold parameters and state are re-exported here.
"""

from torchhys import dynamics, export, fitting, operator, optim, plants, signals, streaming
from torchhys.backlash import Backlash, BacklashCell
from torchhys.cascade import Cascade
from torchhys.drift import Drift, fit_drift
from torchhys.eiho import EIHO, ZhaoTanOperator
from torchhys.generalized_pi import GeneralizedPrandtlIshlinskii, fit_generalized_pi
from torchhys.generalized_pi_inverse import GeneralizedPIInverse
from torchhys.jiles_atherton import JilesAtherton, fit_jiles_atherton
from torchhys.networks import InverseHysteresisNet
from torchhys.operator import HysteresisOperator, OperatorStep, StateBlock, register_operator
from torchhys.prandtl_ishlinskii import PrandtlIshlinskii, PrandtlIshlinskiiInverse
from torchhys.preisach import Preisach, fit_preisach, select_penalty
from torchhys.preisach_inverse import PreisachInverse
from torchhys.stop_pi import StopPrandtlIshlinskii, fit_stop_pi, select_stop_pi_ridge
from torchhys.stop_pi_inverse import StopPIInverse

__version__ = "0.1.0"

__all__ = [
    "__version__",
    "plants",
    "signals",
    "optim",
    "export",
    "fitting",
    "streaming",
    "operator",
    "dynamics",
    "HysteresisOperator",
    "OperatorStep",
    "StateBlock",
    "register_operator",
    "Backlash",
    "Cascade",
    "Drift",
    "fit_drift",
    "EIHO",
    "InverseHysteresisNet",
    "ZhaoTanOperator",
    "BacklashCell",
    "PrandtlIshlinskii",
    "PrandtlIshlinskiiInverse",
    "Preisach",
    "PreisachInverse",
    "JilesAtherton",
    "fit_jiles_atherton",
    "fit_preisach",
    "select_penalty",
    "GeneralizedPIInverse",
    "GeneralizedPrandtlIshlinskii",
    "fit_generalized_pi",
    "StopPIInverse",
    "StopPrandtlIshlinskii",
    "fit_stop_pi",
    "select_stop_pi_ridge",
]
