"""torchhys: differentiable hysteresis and inverse-hysteresis modelling in PyTorch.

The functional core lives in :mod:`torchhys.functional`; the ``nn.Module`` wrappers
that hold parameters and state are re-exported here.
"""

from torchhys import (
    deploy,
    dynamics,
    identification,
    models,
    operator,
    operators,
    optim,
    plants,
    signals,
)
from torchhys._version import __version__
from torchhys.deploy import export, streaming
from torchhys.identification import fitting
from torchhys.identification.drift import fit_drift
from torchhys.identification.generalized_pi import fit_generalized_pi
from torchhys.identification.jiles_atherton import fit_jiles_atherton
from torchhys.identification.preisach import fit_preisach, select_penalty
from torchhys.identification.stop_pi import fit_stop_pi, select_stop_pi_ridge
from torchhys.networks import InverseHysteresisNet
from torchhys.operator import HysteresisOperator, OperatorStep, StateBlock
from torchhys.operators.backlash import Backlash, BacklashCell
from torchhys.operators.cascade import Cascade
from torchhys.operators.drift import Drift
from torchhys.operators.eiho import EIHO, ZhaoTanOperator
from torchhys.operators.eiho_segment import SegmentEIHO
from torchhys.operators.generalized_pi import GeneralizedPIInverse, GeneralizedPrandtlIshlinskii
from torchhys.operators.jiles_atherton import JilesAtherton
from torchhys.operators.prandtl_ishlinskii import PrandtlIshlinskii, PrandtlIshlinskiiInverse
from torchhys.operators.preisach import Preisach, PreisachInverse
from torchhys.operators.stop_pi import StopPIInverse, StopPrandtlIshlinskii
from torchhys.registry import register_operator

__all__ = [
    "__version__",
    "plants",
    "deploy",
    "identification",
    "operators",
    "models",
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
    "SegmentEIHO",
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
