"""torchhys: differentiable hysteresis and inverse-hysteresis modelling in PyTorch.

The functional core lives in :mod:`torchhys.functional`; the ``nn.Module`` wrappers
that hold parameters and state are re-exported here, with the operator protocol. Every
built-in operator is registered (:data:`torchhys.registry.OPERATORS`) when ``torchhys`` is
imported.

The subpackages that not every user needs (``compose``, ``conditions``, ``deploy``, ``dynamics``,
``identification``, ``models``, ``optim``, ``plants``, ``signals``, ``testing``), and the
families' ``fit_*`` and ``select_*``, are loaded on first use (``torchhys.plants`` or
``import torchhys.plants``) where nothing has loaded them before: ``import torchhys`` loads
neither SciPy (the plants' ODE solver), nor a fit, nor Lightning
(:mod:`torchhys.training`, which needs the ``train`` extra, is reached by its own import).
"""

import importlib
import pkgutil
from typing import TYPE_CHECKING, Any

from torchhys import functional, operator, operators, protocols, registry, step
from torchhys._version import __version__
from torchhys.networks import InverseHysteresisNet
from torchhys.operator import HysteresisOperator
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
from torchhys.step import OperatorStep, StateBlock

# the operators' modules register their operators when imported: every one of them, so
# that OPERATORS names every built-in operator whichever the face re-exports
for _module in pkgutil.iter_modules(operators.__path__):
    importlib.import_module(f"{operators.__name__}.{_module.name}")
del _module

_LAZY_SUBPACKAGES = ("compose", "conditions", "datasets", "deploy", "dynamics", "identification",
                     "models", "optim", "plants", "selection", "signals", "testing")
"""Subpackages loaded on first use (:func:`__getattr__`)."""

_LAZY_NAMES = {
    "Compensator": "torchhys.estimator",
    "fit_drift": "torchhys.identification.drift",
    "fit_generalized_pi": "torchhys.identification.generalized_pi",
    "fit_jiles_atherton": "torchhys.identification.jiles_atherton",
    "fit_preisach": "torchhys.identification.preisach",
    "select_penalty": "torchhys.identification.preisach",
    "fit_stop_pi": "torchhys.identification.stop_pi",
    "select_stop_pi_ridge": "torchhys.identification.stop_pi",
}
"""Names loaded on first use, and the module each lives in."""

if TYPE_CHECKING:  # what a type checker and an editor see: the same names, eagerly
    from torchhys import (
        compose,
        conditions,
        datasets,
        deploy,
        dynamics,
        identification,
        models,
        optim,
        plants,
        signals,
        testing,
    )
    from torchhys.estimator import Compensator
    from torchhys.identification.drift import fit_drift
    from torchhys.identification.generalized_pi import fit_generalized_pi
    from torchhys.identification.jiles_atherton import fit_jiles_atherton
    from torchhys.identification.preisach import fit_preisach, select_penalty
    from torchhys.identification.stop_pi import fit_stop_pi, select_stop_pi_ridge

__all__ = [
    "__version__",
    # subpackages and modules
    "compose",
    "conditions",
    "datasets",
    "deploy",
    "dynamics",
    "functional",
    "identification",
    "models",
    "operator",
    "operators",
    "optim",
    "plants",
    "protocols",
    "registry",
    "selection",
    "signals",
    "step",
    "testing",
    # the operator protocol
    "HysteresisOperator",
    "OperatorStep",
    "StateBlock",
    "register_operator",
    # operators
    "Backlash",
    "BacklashCell",
    "Cascade",
    "Drift",
    "EIHO",
    "GeneralizedPIInverse",
    "GeneralizedPrandtlIshlinskii",
    "JilesAtherton",
    "PrandtlIshlinskii",
    "PrandtlIshlinskiiInverse",
    "Preisach",
    "PreisachInverse",
    "SegmentEIHO",
    "StopPIInverse",
    "StopPrandtlIshlinskii",
    "ZhaoTanOperator",
    # the network
    "InverseHysteresisNet",
    # a compensator fitted from arrays in one call
    "Compensator",
    # identification
    "fit_drift",
    "fit_generalized_pi",
    "fit_jiles_atherton",
    "fit_preisach",
    "fit_stop_pi",
    "select_penalty",
    "select_stop_pi_ridge",
]


def __getattr__(name: str) -> Any:
    """Load a subpackage or a family's fit on first use (PEP 562); the value is kept."""
    if name in _LAZY_SUBPACKAGES:
        value = importlib.import_module(f"{__name__}.{name}")
    elif name in _LAZY_NAMES:
        value = getattr(importlib.import_module(_LAZY_NAMES[name]), name)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
