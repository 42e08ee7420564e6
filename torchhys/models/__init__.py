"""Dynamic models with hysteresis identified from one input-output record.

- :class:`BoucWenOscillator`: the grey-box Bouc-Wen oscillator (RK4 substeps, float64).
- :class:`HysteresisFeedback`: a block-oriented black-box model, linear blocks with a
  hysteretic feedback (the registered operators ``duhem`` and ``play_hysteresis``:
  :class:`torchhys.operators.duhem.DuhemHysteresis`,
  :class:`torchhys.operators.play_hysteresis.PlayHysteresis`; their earlier paths
  ``torchhys.models.DuhemHysteresis`` and ``torchhys.models.PlayHysteresis`` still work, with
  a :class:`DeprecationWarning`).
- :class:`LinearModel` and :func:`fit_linear`: the linear baseline.
- :func:`fit_windows` (windows side by side with carried states), :func:`simulate`.

All map a force sequence u to a displacement y with a carried state:
``model(u, state=None) -> (y, state)``, chunked calls equal one call.
"""

from torchhys._deprecated import moved as _moved
from torchhys.models.block_oriented import HysteresisFeedback
from torchhys.models.bouc_wen_oscillator import BENCHMARK, BoucWenOscillator
from torchhys.models.linear import LinearModel, fit_linear
from torchhys.models.starting_values import grey_box_start, init_from_linear
from torchhys.models.windows import WindowFit, check_record, fit_windows, simulate

__all__ = [
    "BENCHMARK",
    "BoucWenOscillator",
    "HysteresisFeedback",
    "LinearModel",
    "WindowFit",
    "check_record",
    "fit_linear",
    "fit_windows",
    "grey_box_start",
    "init_from_linear",
    "simulate",
]

__getattr__ = _moved(__name__, {
    "DuhemHysteresis": "torchhys.operators.duhem",
    "PlayHysteresis": "torchhys.operators.play_hysteresis",
})
