"""Pure tensor functions: the functional core of torchhys."""

from torchhys.functional.backlash import backlash, play_step
from torchhys.functional.prandtl_ishlinskii import (
    prandtl_ishlinskii,
    prandtl_ishlinskii_inverse_parameters,
)

__all__: list[str] = [
    "backlash",
    "play_step",
    "prandtl_ishlinskii",
    "prandtl_ishlinskii_inverse_parameters",
]
