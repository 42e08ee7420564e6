"""Pure tensor functions: the functional core of torchhys."""

from torchhys.functional._branch import BranchState
from torchhys.functional.adaptive import nlms_update, rls_update
from torchhys.functional.backlash import backlash, play_step
from torchhys.functional.drift import accumulated_variation, drift
from torchhys.functional.eiho import NonCausalWarning, eiho, segment_coefficients, zhao_tan
from torchhys.functional.jiles_atherton import jiles_atherton, jiles_atherton_step
from torchhys.functional.linear_filter import lfilter
from torchhys.functional.prandtl_ishlinskii import (
    prandtl_ishlinskii,
    prandtl_ishlinskii_inverse_parameters,
)
from torchhys.functional.preisach import (
    demagnetized_state,
    preisach,
    preisach_grid,
    relay_states,
    relay_update,
)
from torchhys.functional.stop_pi import stop_characteristic, stop_pi, stop_pi_inverse
from torchhys.functional.turning_points import (
    Branches,
    estimate_threshold,
    reversal_ranges,
    turning_points,
)

__all__: list[str] = [
    "BranchState",
    "nlms_update",
    "rls_update",
    "Branches",
    "accumulated_variation",
    "drift",
    "NonCausalWarning",
    "eiho",
    "estimate_threshold",
    "reversal_ranges",
    "segment_coefficients",
    "turning_points",
    "zhao_tan",
    "backlash",
    "play_step",
    "prandtl_ishlinskii",
    "prandtl_ishlinskii_inverse_parameters",
    "demagnetized_state",
    "lfilter",
    "jiles_atherton",
    "jiles_atherton_step",
    "preisach",
    "preisach_grid",
    "relay_states",
    "relay_update",
    "stop_characteristic",
    "stop_pi",
    "stop_pi_inverse",
]
