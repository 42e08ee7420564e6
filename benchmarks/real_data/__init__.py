"""Held-out accuracy of hysteresis models on measured recordings (see docs/real-data.md).

For every measured data set (``examples/data/real/``, the MnZn ferrite loops of
``../shared/data/``, a piezo actuator's record read from ``--piezo`` and an accelerator
quadrupole's magnetic measurements read from ``--quad`` when given), with
the protocol its README suggests, each model is fitted on the training part, its settings
(size, penalty, iterations, direction) are chosen on a time-ordered hold-out inside the
training part (the last quarter of the scored samples of every training row), it is
refitted on the whole training part with those settings, and it is scored once on the
held-out recordings. Reported: RMSE in the target's units and ``ratio`` = RMSE / min(line
RMSE, poly RMSE) (below 1: better than both memoryless baselines); ``choice`` says what the
hold-out selected and the hold-out RMSE.

    python -m benchmarks.real_data [--data NAME ...] [--out table.csv] [--quick]
        [--ferrite PATH] [--piezo PATH] [--quad DIR] [--config configs/measured.yaml]
        [--models MODEL ...] [--jobs N]
    python -m benchmarks.real_data --tables table.csv ...

Models (all causal; a row starts from a zero state, its first ``warmup`` samples only run
the states and are neither fitted nor scored):

- ``line``: least-squares line of the target in the input; ``poly``: polynomial, degree
  1..9 chosen on the hold-out (both memoryless);
- ``pi_constrained``: ``fit_prandtl_ishlinskii(nonnegative=True)`` on ``play_width_grid``,
  either of the target from the input ("direct") or of the input from the target, then its
  exact inverse ("inverse of forward"), and of the target or of its negative: a
  non-negative PI model only draws loops that run anticlockwise in its (input, output)
  plane, with branches that steepen after a reversal; its inverse draws clockwise ones that
  flatten, and the negation flips either. Direction, sign, number of widths, grid power and
  ridge chosen on the hold-out;
- ``pi_ls``: the same direct fit, unconstrained (the operator of ``configs/measured.yaml``);
- ``generalized_pi``: ``fit_generalized_pi`` in either direction (the inverse: the exact
  ``.inverse()``, the output function's inverse bounded to the PI part's training range
  plus half its span on each side, as ``configs/measured.yaml``'s ``gpi``), of the target times
  the sign that makes it rise with the input, on the widths and ridge chosen for the
  non-negative PI fit of that direction and sign; direction and number of tanh units chosen
  on the hold-out (a refit that diverges passes to the next candidate);
- ``preisach``: ``fit_preisach`` on a grid over the training input range; levels,
  smoothness penalty and the sign of the target (a non-negative density draws loops of one
  orientation; its free linear term lets the negated fit draw the other) chosen on the
  hold-out;
- ``stop_pi``: ``fit_stop_pi`` (non-negative slopes) of the target or of its negative, on
  ``play_width_grid`` thresholds; their number, the grid power, the characteristic segments,
  the sign and the ridge chosen on the hold-out;
- ``stop_pi_drift``: those stops beside the configs' ``drift`` family (``fit_drift``: a drift
  of the accumulated input variation beside a free slope), an affine least-squares readout
  of the two; the stops' settings chosen on the hold-out of the whole;
- ``jiles_atherton``: ``fit_jiles_atherton`` (the inverse Jiles-Atherton model, five physical
  parameters, Levenberg-Marquardt from 8 starts) in physical units, on the B -> H records
  only (n/a elsewhere); nothing to choose, the hold-out RMSE is that of the fit before it;
- ``eiho_net``: ``InverseHysteresisNet([EIHO(a=1, rule="recent", output="branch"),
  Backlash(16 widths 0.4 span k/16)], hidden=16)``, trained full-batch with L-BFGS; the number
  of L-BFGS steps and the EIHO's reversal threshold (0 or "auto") chosen on the hold-out;
- ``default``: what ``configs/measured.yaml`` (or ``--config``) chooses: its candidates
  (``model.select``) are each scored as the config's ``model.select_cv`` says, as
  ``torchhys fit`` scores them (``measured.yaml``: 4-fold blocked cross-validation inside the
  training rows; without ``select_cv``: fitted on the part before the hold-out and scored on
  it), the config's ``select_rule`` picks one, which is built through ``build_operators`` +
  ``fit_data_dependent``, trained as the config says (its optimizer, one full-batch step per
  epoch, ``trainer.max_epochs``, the last epoch kept, capped in time) on the whole training
  part, and scored by its output saturated to the training target range
  (:func:`~torchhys.deploy.ranges.default_limits`, the exported command limits; the exported
  compensator's input clamp and direction guard on top of it: ``benchmarks/deploy_safety.py``);
- ``selected``: the row above with the least hold-out RMSE (for ``default``: its chosen
  candidate's, fitted before the hold-out; a model-family choice made on the training part
  only).

Every model but ``line``, ``poly`` and ``default`` sees the input divided by its training
standard deviation and the standardized target (training statistics), so that grids and
penalties mean the same on every data set; ``default`` sees physical units, as
``torchhys fit`` does.

The package: :mod:`.datasets` (the recordings and each protocol's split), :mod:`.protocols`
(the protocols by name, the files they read), :mod:`.scoring` (budgets, fitted models, the
hold-out and the held-out RMSE), :mod:`.baselines` (``line``, ``poly``), :mod:`.families`
(the rows of the hysteresis model families: each runs its family's own search,
:data:`torchhys.registry.SEARCHES`, over the budget's sizes; the EIHO network's row),
:mod:`.default_row` (``default``: a
``torchhys fit`` config trained as it says), :mod:`.rows` (one protocol's table),
:mod:`.report` (the markdown table, the targets' tally, saved tables) and :mod:`.cli` (the
command line; ``__main__``).
"""

from .baselines import line, poly
from .cli import main, run_in_processes
from .datasets import (
    F64,
    FERRITE,
    PIEZO,
    QUAD,
    QUAD_RUNS,
    REAL,
    ROOT,
    SEALS,
    Split,
    ferrite,
    forc,
    friction_damper,
    jamodel,
    micromanipulator,
    mr_damper,
    piezo,
    pneumatic,
    quad,
    quad_files,
    read_csv,
    read_piezo,
    read_slac_run,
    sma,
)
from .default_row import CONFIG, default, default_net
from .families import (
    RIDGES,
    SMOOTHNESS,
    eiho_net,
    generalized_pi,
    jiles_atherton,
    pi_constrained,
    pi_ls,
    preisach,
    stop_pi,
    stop_pi_drift,
)
from .protocols import DATASETS, Files, Protocol, shortened, tiled
from .report import FAMILIES, TARGET, markdown, read_tables, targets
from .rows import COLUMNS, MODELS, evaluate
from .scoring import (
    FULL,
    QUICK,
    Budget,
    Fitted,
    NotApplicable,
    Predict,
    Scaled,
    holdout,
    scaled,
    test_rmse,
)

__all__ = [
    "COLUMNS", "CONFIG", "DATASETS", "F64", "FAMILIES", "FERRITE", "FULL", "MODELS", "PIEZO",
    "QUAD", "QUAD_RUNS", "QUICK", "REAL", "RIDGES", "ROOT", "SEALS", "SMOOTHNESS", "TARGET",
    "Budget", "Files", "Fitted", "NotApplicable", "Predict", "Protocol", "Scaled", "Split",
    "default", "default_net", "eiho_net", "evaluate", "ferrite", "forc", "friction_damper",
    "generalized_pi", "holdout", "jamodel", "jiles_atherton", "line", "main", "markdown",
    "micromanipulator", "mr_damper", "pi_constrained", "pi_ls", "piezo", "pneumatic", "poly",
    "preisach", "quad", "quad_files", "read_csv", "read_piezo", "read_slac_run", "read_tables",
    "run_in_processes", "scaled", "shortened", "sma", "stop_pi", "stop_pi_drift", "targets",
    "test_rmse", "tiled",
]
