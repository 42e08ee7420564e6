"""torchhys: differentiable hysteresis and inverse-hysteresis modelling in PyTorch.

The functional core lives in :mod:`torchhys.functional`; the ``nn.Module`` wrappers
that hold parameters and state are re-exported here.
"""

from torchhys import (
    deploy,
    dynamics,
    identification,
    operator,
    operators,
    optim,
    plants,
    signals,
)
from torchhys.deploy import export, streaming
from torchhys.identification import fitting
from torchhys.networks import InverseHysteresisNet
from torchhys.operator import HysteresisOperator, OperatorStep, StateBlock, register_operator
from torchhys.operators.backlash import Backlash, BacklashCell
from torchhys.operators.cascade import Cascade
from torchhys.operators.drift import Drift, fit_drift
from torchhys.operators.eiho import EIHO, ZhaoTanOperator
from torchhys.operators.generalized_pi import GeneralizedPrandtlIshlinskii, fit_generalized_pi
from torchhys.operators.generalized_pi_inverse import GeneralizedPIInverse
from torchhys.operators.jiles_atherton import JilesAtherton, fit_jiles_atherton
from torchhys.operators.prandtl_ishlinskii import PrandtlIshlinskii, PrandtlIshlinskiiInverse
from torchhys.operators.preisach import Preisach, fit_preisach, select_penalty
from torchhys.operators.preisach_inverse import PreisachInverse
from torchhys.operators.stop_pi import StopPrandtlIshlinskii, fit_stop_pi, select_stop_pi_ridge
from torchhys.operators.stop_pi_inverse import StopPIInverse

__version__ = "0.1.0"

__all__ = [
    "__version__",
    "plants",
    "deploy",
    "identification",
    "operators",
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
