"""Dynamic models with hysteresis identified from one input-output record.

- :class:`BoucWenOscillator`: the grey-box Bouc-Wen oscillator (RK4 substeps, float64).
- :class:`HysteresisFeedback`: a block-oriented black-box model, linear blocks with a
  hysteretic feedback (:class:`DuhemHysteresis` or :class:`PlayHysteresis`).
- :class:`LinearModel` and :func:`fit_linear`: the linear baseline.
- :func:`fit_windows` (windows side by side with carried states), :func:`simulate`.

All map a force sequence u to a displacement y with a carried state:
``model(u, state=None) -> (y, state)``, chunked calls equal one call.
"""

from torchhys.models.block_oriented import HysteresisFeedback
from torchhys.models.bouc_wen_oscillator import BENCHMARK, BoucWenOscillator
from torchhys.models.linear import LinearModel, fit_linear
from torchhys.models.starting_values import grey_box_start, init_from_linear
from torchhys.models.windows import WindowFit, check_record, fit_windows, simulate
from torchhys.operators.duhem import DuhemHysteresis
from torchhys.operators.play_hysteresis import PlayHysteresis

__all__ = [
    "BENCHMARK",
    "BoucWenOscillator",
    "DuhemHysteresis",
    "HysteresisFeedback",
    "LinearModel",
    "PlayHysteresis",
    "WindowFit",
    "check_record",
    "fit_linear",
    "fit_windows",
    "grey_box_start",
    "init_from_linear",
    "simulate",
]
