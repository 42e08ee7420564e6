"""Constrained model families as config operators, identified on the training split.

Each spec builds an operator whose output is a fitted model of the target (in standardized
units; ``jiles_atherton`` in the target's physical units); the network that reads it
(``hidden: 1, activation: identity`` for a plain affine readout, whose normalization
standardizes the operator's output) maps it back. They are the candidates of
``configs/measured.yaml`` and ``configs/magnetic.yaml``:

- ``{"fit": "pi_nonneg", "n_widths": 10, "power": 2.0, "ridge": "auto",
  "direction": "direct"}``: a Prandtl-Ishlinskii model with non-negative weights
  (:func:`torchhys.identification.fitting.fit_prandtl_ishlinskii` with
  ``nonnegative=True``) of the target from the input (``direct``), or of the input from the
  target, then its exact inverse
  (``inverse``). Such a model draws loops of one orientation only, so the target's sign is
  chosen by the training fit (both signs are fitted).
- ``{"fit": "gpi", "n_widths": 10, "power": 2.0, "ridge": "auto", "units": 4,
  "epochs": 1000, "sample_iterations": 1e7, "direction": "direct"}``:
  :func:`torchhys.fit_generalized_pi` of the target (times the sign that makes it rise with
  the input) from the input, or of the input from it, then
  :class:`torchhys.GeneralizedPIInverse`. Its L-BFGS iterations are at most ``epochs`` and
  at most ``sample_iterations`` over the fitted samples (at least 20): a long record gets
  fewer (100 on 1e5 fitted samples), records up to 1e4 samples all of them.
- ``{"fit": "preisach", "n": 20, "smoothness": "auto", "grading": None,
  "direction": "direct"}``: :func:`torchhys.fit_preisach` of the target from the input on a
  grid over the input's training range (``direct``), or of the input from the target, then
  its exact inverse (``inverse``, :class:`torchhys.PreisachInverse`: a magnetic core's flux
  density from its field, inverted into the compensator); both signs of the target fitted,
  the better kept. ``grading``: None for an even grid, or a graded one whose ``scale`` is
  that fraction of half the grid's span (:class:`torchhys.Preisach`).
- ``{"fit": "stop_pi", "n_widths": 20, "power": 2.0, "segments": 4, "ridge": "auto", "nonnegative":
  True}``: :func:`torchhys.fit_stop_pi`, stop operators with thresholds on
  :func:`~torchhys.identification.fitting.play_width_grid` of the input (up to its span: the largest
  make the memoryless part), each through a piecewise-linear characteristic of ``segments`` equal
  segments (non-negative slopes: a friction element with a nonlinear spring, whose loops run
  clockwise); both signs of the target fitted, the better kept.
- ``{"fit": "jiles_atherton", "mu0": 4e-7 pi, "starts": 8, "iterations": 60,
  "substeps": None}``: :func:`torchhys.fit_jiles_atherton`, the inverse Jiles-Atherton model
  of a magnetic core (the input the flux density B, the target the field H), fitted to the
  target in its physical units (``mu0``: input units per target unit of free space, the
  default for B in T and H in A/m). ``substeps`` (Euler steps per sample; None: enough that
  a sample step of the 0.99 quantile moves the input by at most 1/32 of its range, so that
  a few large jumps do not multiply the cost).
- ``{"fit": "drift", "scales": [0.5, 1, 2, 4, 8, 16, 32]}``: :func:`torchhys.fit_drift`, a
  monotone, decelerating drift of the target with the input's accumulated variation
  (saturation scales in spans of the scored training input), weights of one sign; beside a
  hysteresis model in one candidate (``[{fit: stop_pi}, {fit: drift}]``, one affine
  readout of both) it shifts the loop as the device is used (the ratcheting of a
  shape-memory alloy). It is fitted beside a free slope in the input (not part of the
  drift), so that a loop's rise and fall with the input is not taken for a drift.

``ridge``/``smoothness: "auto"`` picks the penalty on a time-ordered hold-out inside the training
split (the last quarter of each row's scored samples; :func:`select_pi_ridge`,
:func:`select_penalty`; for ``gpi``, whose fit can stop at a poor local optimum, the next best
ridges on that hold-out are tried in turn when the fit fails, unless it ended on the straight
line itself: :attr:`~torchhys.identification.errors.NoBetterThanLine.on_the_line`). Every
choice uses the training split only. Widths come from
:func:`~torchhys.identification.fitting.play_width_grid` of the fitted model's input. A fit that
cannot exist (no inverse, a target that does not rise, a diverged fit) raises
:class:`~torchhys.identification.errors.FitError`: model selection scores that candidate as
failed.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import Tensor, nn

from torchhys import (
    Drift,
    GeneralizedPIInverse,
    GeneralizedPrandtlIshlinskii,
    JilesAtherton,
    PrandtlIshlinskii,
    Preisach,
    PreisachInverse,
    StopPrandtlIshlinskii,
    fit_drift,
    fit_generalized_pi,
    fit_jiles_atherton,
)
from torchhys._checks import (
    check_bool,
    check_choice,
    check_int,
    check_nonnegative,
    check_positive,
)
from torchhys._memory import check_memory
from torchhys.functional.jiles_atherton import MU0
from torchhys.identification.errors import (
    FitError,
    NoBetterThanLine,
    _checked,
    _rmse,
    _samples,
    _standardized,
)
from torchhys.identification.fitting import fit_prandtl_ishlinskii, play_width_grid, select_pi_ridge
from torchhys.identification.jiles_atherton import substeps_for
from torchhys.identification.preisach import check_fit_memory, fit_preisach_signs
from torchhys.identification.stop_pi import fit_stop_pi_signs

__all__ = ["FAMILIES", "GPI_SAMPLE_ITERATIONS", "PENALTIES", "fit_key"]

PENALTIES = (0.0, 1e-8, 1e-6, 1e-4, 1e-2, 1e-1)
"""The grid of ``ridge``/``smoothness: "auto"``."""
VALIDATION = 0.25
"""The hold-out share of ``"auto"`` penalties: the last quarter of each row's scored
samples."""

GPI_SAMPLE_ITERATIONS = 1e7
"""The ``gpi`` family's bound on L-BFGS iterations times fitted samples (its
``sample_iterations``)."""

Fitter = Callable[[Tensor, Tensor, int, Tensor | None], nn.Module]


def _keys(spec: Mapping[str, Any], allowed: set[str]) -> None:
    unknown = sorted(set(spec) - allowed - {"fit"})
    if unknown:
        raise ValueError(
            f"fit {spec['fit']!r}: unknown option(s) {unknown}; valid: {sorted(allowed)}"
        )


def _penalty(spec: Mapping[str, Any], key: str) -> float | str:
    value = spec.get(key, "auto")
    if value == "auto":
        return value
    return check_nonnegative(value, f"fit {spec['fit']!r}: {key}",
                             alternatives="'auto' or ")


FIT_BYTES = 8 * 12
"""Bytes a fit takes per column (a play or stop of the grid, a unit of ``gpi``) and fitted
sample: float64 columns times 12, measured on real fits (pi_nonneg, gpi and stop_pi, 2000
columns of 2000 samples: 9 to 11.5 times the float64 columns at their peak)."""
PLACEHOLDER_BYTES = 16
"""Bytes of the placeholder operator per column (its widths built as int64, then float32
widths and weights), before any data are seen."""


def _check_columns(spec: Mapping[str, Any], columns: int, what: str,
                   samples: int | None = None) -> None:
    """Refuse a spec whose ``columns`` (``what``: the option) would take more than the memory
    limit: its placeholder (``samples`` None: when the spec is read) or its fit on
    ``samples`` samples (:data:`FIT_BYTES`), before allocating."""
    nbytes = columns * (PLACEHOLDER_BYTES if samples is None else FIT_BYTES * samples)
    on = "" if samples is None else f" fitted on {samples} samples"
    check_memory(nbytes, f"fit {spec['fit']!r}: {what} ({columns} columns){on}",
                 "lower " + " or ".join(re.findall(r"(\w+)=", what)))


def _grid(spec: Mapping[str, Any], n_default: int) -> tuple[int, float, str]:
    n = check_int(spec.get("n_widths", n_default), f"fit {spec['fit']!r}: n_widths",
                  minimum=1)
    if spec["fit"] == "pi_nonneg":
        _check_columns(spec, n, f"n_widths={n}")
    power = check_positive(spec.get("power", 2.0), f"fit {spec['fit']!r}: power")
    direction = check_choice(spec.get("direction", "direct"),
                             f"fit {spec['fit']!r}: direction", ["direct", "inverse"])
    return n, power, direction


def _holdout(scored: Tensor) -> float:
    """:data:`VALIDATION`, the share of each row's scored samples (the mask given to
    ``select_pi_ridge`` / ``select_penalty``) held out to choose a penalty.

    Raises:
        FitError: fewer than 8 scored samples (no hold-out to choose a penalty on).
    """
    n = int(scored.sum())
    if n < 8:
        raise FitError(f"{n} scored training samples are too few to choose a penalty "
                       "on a hold-out; give the penalty as a number")
    return VALIDATION


def _pi_fit(u: Tensor, out: Tensor, widths: Tensor, ridge: float | str,
            scored: Tensor) -> PrandtlIshlinskii:
    if ridge == "auto":
        ridge, _ = select_pi_ridge(u, out, widths, PENALTIES, nonnegative=True,
                                   validation=_holdout(scored), mask=scored)
    return fit_prandtl_ishlinskii(u, out, widths, ridge=ridge, mask=scored, nonnegative=True)


def _pi_nonneg(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"n_widths", "power", "ridge", "direction"})
    n, power, direction = _grid(spec, 10)
    ridge = _penalty(spec, "ridge")

    def one_sign(x: Tensor, t: Tensor, sx: float, scored: Tensor, known: Tensor) -> nn.Module:
        """The PI model of t from x (physical input units)."""
        if direction == "direct":
            m = _pi_fit(x / sx, t, play_width_grid((x / sx)[known], n, power=power), ridge,
                        scored)
            return PrandtlIshlinskii(m.get_widths() * sx, m.weights / sx,
                                     linear_weight=float(m.linear_weight) / sx)
        # the forward model of the centred, scaled input (a PI model has no offset), and its
        # exact inverse after the input map (x - mx) / sx: a GeneralizedPIInverse whose g is
        # the affine map sx v + mx
        mx = float(x[scored].mean())
        forward = _pi_fit(t, (x - mx) / sx, play_width_grid(t[known], n, power=power), ridge,
                          scored)
        try:
            return GeneralizedPrandtlIshlinskii(
                forward.get_widths(), forward.weights, centers=[], gain=sx, offset=mx,
                linear_weight=float(forward.linear_weight)).inverse()
        except ValueError as err:
            raise FitError(f"pi_nonneg inverse: {err}") from None

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        _check_columns(spec, n, f"n_widths={n}", x.numel())
        scored, known = _samples(x, warmup, mask)
        sx, t = _standardized(x, y, scored)
        fits = []
        for sign in (1.0, -1.0):
            try:
                m = one_sign(x, sign * t, sx, scored, known)
            except FitError:
                continue
            with torch.no_grad():
                m.weights.mul_(sign)
                m.linear_weight.mul_(sign)
            fits.append((_rmse(m, x, t, scored), sign, m))
        if not fits:
            raise FitError(f"pi_nonneg ({direction}): no invertible fit of either sign")
        rmse, _, m = min(fits, key=lambda f: f[0])
        return _checked(m, x, t, scored, "pi_nonneg", rmse=rmse)

    placeholder: nn.Module = (PrandtlIshlinskii(torch.arange(1, n + 1) / n, torch.zeros(n))
                              if direction == "direct" else GeneralizedPIInverse(n, 0))
    return placeholder, fit


def _gpi_iterations(epochs: int, work: float, scored: int) -> int:
    """The L-BFGS iterations of a ``gpi`` fit on ``scored`` samples."""
    return min(epochs, max(20, int(work / scored)))


def fit_key(spec: Mapping[str, Any], x: Tensor, warmup: int,
            mask: Tensor | None) -> dict[str, Any]:
    """The spec as it determines the fit on these data (for sharing fits between
    candidates, :mod:`torchhys.identification._fit_cache`): a ``gpi`` spec with ``epochs`` the
    iterations it runs on these samples and no ``sample_iterations`` (on a long record the
    spec with ``epochs: 200`` and the default one run the same fit); others as given."""
    key = dict(spec)
    if key.get("fit") == "gpi":
        scored, _ = _samples(x.reshape(-1, x.shape[-1]), warmup, mask)
        work = key.pop("sample_iterations", GPI_SAMPLE_ITERATIONS)
        key["epochs"] = _gpi_iterations(key.get("epochs", 1000), work, int(scored.sum()))
    return key


def _gpi(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"n_widths", "power", "ridge", "units", "epochs", "sample_iterations",
                 "direction"})
    n, power, direction = _grid(spec, 10)
    ridge = _penalty(spec, "ridge")
    units = check_int(spec.get("units", 4), "fit 'gpi': units", minimum=0)
    _check_columns(spec, n + units, f"n_widths={n} + units={units}")
    epochs = check_int(spec.get("epochs", 1000), "fit 'gpi': epochs", minimum=1)
    work = check_positive(spec.get("sample_iterations", GPI_SAMPLE_ITERATIONS),
                          "fit 'gpi': sample_iterations")

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        _check_columns(spec, n + units, f"n_widths={n} + units={units}", x.numel())
        scored, known = _samples(x, warmup, mask)
        sx, t = _standardized(x, y, scored)
        xs, ts = (x / sx)[scored], t[scored]
        t = t if float(((xs - xs.mean()) * ts).sum()) >= 0 else -t  # rising with x
        mx = float(x[scored].mean())  # the inverse route fits the centred input
        u, out = (x / sx, t) if direction == "direct" else (t, (x - mx) / sx)
        widths = play_width_grid(u[known], n, power=power)
        ridges = [ridge]
        if ridge == "auto":
            _, scores = select_pi_ridge(u, out, widths, PENALTIES, nonnegative=True,
                                        validation=_holdout(scored), mask=scored)
            # the local optimum of the fit depends on its start (the initial PI fit): if the
            # fit with the best ridge fails, the next best start it elsewhere
            ridges = sorted(scores, key=lambda r: scores[r])[:3]
        errors = []
        for r in ridges:
            try:
                return fitted(x, t, u, out, widths, r, sx, mx, scored, known)
            except (ValueError, FloatingPointError) as err:  # FitError, diverged, no inverse
                errors.append(f"ridge {r:g}: {err}")
                if isinstance(err, NoBetterThanLine) and err.on_the_line:
                    errors.append("the fit ended on the line: no other start tried")
                    break
        raise FitError(f"gpi ({direction}): " + "; ".join(errors))

    def fitted(x: Tensor, t: Tensor, u: Tensor, out: Tensor, widths: Tensor, r: float,
               sx: float, mx: float, scored: Tensor, known: Tensor) -> nn.Module:
        iterations = _gpi_iterations(epochs, work, int(scored.sum()))
        m = fit_generalized_pi(u, out, widths, units=units, ridge=r, lbfgs_epochs=iterations,
                               mask=scored)
        pw, w, w0, a, c, b, s, off = (v.detach() for v in m.parameters_effective())
        if direction == "direct":  # the same model of the physical input x
            return _checked(GeneralizedPrandtlIshlinskii(
                pw * sx, w / sx, linear_weight=float(w0) / sx, centers=b, slopes=s,
                unit_weights=c, gain=float(a), offset=float(off)), x, t, scored, "the model")
        # The same model, rewritten for a well-conditioned inverse: the PI part divided by k
        # (its training std), g(k v) in its place, scaled by sx and shifted by mx so that it
        # maps to the physical input. g^-1 is bounded to the PI part's training
        # range with a margin of half its span on each side.
        with torch.no_grad():
            p = m.prandtl_ishlinskii()(u)[0]
        k = float(p[known].std().clamp_min(1e-300))
        scaled = GeneralizedPrandtlIshlinskii(
            pw, w / k, linear_weight=float(w0) / k, centers=b / k, slopes=s * k,
            unit_weights=c * sx, gain=float(a) * k * sx, offset=float(off) * sx + mx)
        return _checked(scaled.bounded_inverse(u[known], pi_output=(p / k)[known]), x, t,
                        scored, "the inverse")

    if direction == "direct":
        placeholder: nn.Module = GeneralizedPrandtlIshlinskii(
            torch.arange(1, n + 1) / n, centers=torch.zeros(units))
    else:
        placeholder = GeneralizedPIInverse(n, units)
    return placeholder.requires_grad_(False), fit


def _preisach(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"n", "smoothness", "grading", "direction"})
    n = check_int(spec.get("n", 20), "fit 'preisach': n", minimum=2)
    check_fit_memory(n, "fit 'preisach'")
    smoothness = _penalty(spec, "smoothness")
    grading = spec.get("grading")
    if grading is not None:
        grading = check_positive(grading, "fit 'preisach': grading (or null)")
    direction = check_choice(spec.get("direction", "direct"), "fit 'preisach': direction",
                             ["direct", "inverse"])

    def fitted(u: Tensor, out: Tensor, scored: Tensor, known: Tensor,
               signs: tuple[float, ...]) -> list[tuple[float, Preisach, float]]:
        """The Preisach models of ``sign * out`` from ``u`` on a grid over u's (known) range,
        one pass of the relays for all signs."""
        lo, hi = float(u[known].min()), float(u[known].max())
        scale = None if grading is None else grading * 0.5 * (hi - lo)
        penalties = list(PENALTIES) if smoothness == "auto" else smoothness
        validation = _holdout(scored) if smoothness == "auto" else VALIDATION
        return fit_preisach_signs(
            u, out, penalties, signs=signs, kind="smoothness", validation=validation, lo=lo,
            hi=hi, n=n, mask=scored, scale=scale)

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        scored, known = _samples(x, warmup, mask)
        sx, t = _standardized(x, y, scored)
        mx = float(x[scored].mean())
        fits = []
        direct = fitted(x, t, scored, known, (1.0, -1.0)) if direction == "direct" else None
        for i, sign in enumerate((1.0, -1.0)):
            if direct is not None:
                _, m, rmse = direct[i]  # its RMS error from the fit's moments
                fits.append((rmse, sign, m))
                continue
            # the model of the centred, scaled input from sign x the target, mapped back to
            # the physical input, then inverted
            (_, forward, _), = fitted(sign * t, (x - mx) / sx, scored, known, (1.0,))
            with torch.no_grad():
                forward.weights.mul_(sx)
                forward.linear.mul_(sx)
                forward.offset.mul_(sx).add_(mx)
            try:
                m = forward.inverse()
            except ValueError:
                continue
            fits.append((_rmse(m, x, sign * t, scored), sign, m))
        if not fits:
            raise FitError(f"preisach ({direction}): no invertible fit of either sign")
        rmse, sign, m = min(fits, key=lambda f: f[0])
        return _checked(m, x, sign * t, scored, "preisach", rmse=rmse)

    placeholder = Preisach(0.0, 1.0, n) if direction == "direct" else PreisachInverse(n)
    return placeholder.requires_grad_(False), fit


def _stop_pi(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"n_widths", "power", "segments", "ridge", "nonnegative"})
    n = check_int(spec.get("n_widths", 20), "fit 'stop_pi': n_widths", minimum=1)
    power = check_positive(spec.get("power", 2.0), "fit 'stop_pi': power")
    segments = check_int(spec.get("segments", 4), "fit 'stop_pi': segments", minimum=1)
    nonnegative = check_bool(spec.get("nonnegative", True), "fit 'stop_pi': nonnegative")
    ridge = _penalty(spec, "ridge")
    _check_columns(spec, n * segments, f"n_widths={n} x segments={segments}")

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        _check_columns(spec, n * segments, f"n_widths={n} x segments={segments}", x.numel())
        scored, _ = _samples(x, warmup, mask)
        sx, t = _standardized(x, y, scored)
        u = x / sx
        thresholds = play_width_grid(u[scored], n, power=power)
        fits = []
        signs = (1.0, -1.0) if nonnegative else (1.0,)
        auto = ridge == "auto"
        models = fit_stop_pi_signs(u, t, thresholds, list(PENALTIES) if auto else ridge,
                                   signs=signs, segments=segments, nonnegative=nonnegative,
                                   validation=_holdout(scored) if auto else VALIDATION,
                                   mask=scored)
        for sign, (_, m, rmse) in zip(signs, models, strict=True):
            # the same model of the physical input x, times the sign
            m = StopPrandtlIshlinskii(
                m.thresholds * sx, sign * m.weights / sx, center=float(m.center) * sx,
                linear_weight=sign * float(m.linear_weight) / sx, offset=sign * float(m.offset))
            fits.append((rmse, m))
        rmse, m = min(fits, key=lambda f: f[0])
        return _checked(m, x, t, scored, "stop_pi", rmse=rmse)

    return StopPrandtlIshlinskii(torch.arange(1, n + 1) / n,
                                 torch.zeros(n, segments)).requires_grad_(False), fit


DRIFT_SCALES = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)
"""Saturation scales of the ``drift`` family, in spans of the scored training input (a full
cycle over the span adds two spans to the accumulated variation)."""


def _drift(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"scales"})
    scales = spec.get("scales", DRIFT_SCALES)
    if (isinstance(scales, (str, bytes)) or not hasattr(scales, "__len__")
            or len(scales) == 0):
        raise ValueError(f"fit 'drift': scales must be a non-empty list of positive "
                         f"numbers (spans of the training input), got {scales!r}")
    mult = [check_positive(c, "fit 'drift': scales[]") for c in scales]

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        scored, _ = _samples(x, warmup, mask)
        _, t = _standardized(x, y, scored)
        span = float(x[scored].max() - x[scored].min())
        return fit_drift(x, t, [span * c for c in mult], mask=scored)

    return Drift(torch.ones(len(mult))).requires_grad_(False), fit


def _substeps(x: Tensor) -> int:
    """Euler steps per sample from the 0.99 quantile of the sample steps
    (:func:`~torchhys.identification.jiles_atherton.substeps_for`). The largest steps are left
    out: a few jumps would set the count (and the cost of every fit) for all samples."""
    return substeps_for(x, quantile=0.99)


def _jiles_atherton(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"mu0", "starts", "iterations", "substeps"})
    mu0 = check_positive(spec.get("mu0", MU0), "fit 'jiles_atherton': mu0")
    starts = check_int(spec.get("starts", 8), "fit 'jiles_atherton': starts", minimum=1)
    iterations = check_int(spec.get("iterations", 60), "fit 'jiles_atherton': iterations",
                           minimum=1)
    substeps = spec.get("substeps")
    if substeps is not None:
        substeps = check_int(substeps, "fit 'jiles_atherton': substeps", minimum=1)

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        scored, _ = _samples(x, warmup, mask)
        _, t = _standardized(x, y, scored)
        try:
            m = fit_jiles_atherton(x, y, warmup=warmup, mask=mask, mu0=mu0, starts=starts,
                                   iterations=iterations,
                                   substeps=_substeps(x) if substeps is None else substeps)
        except (ValueError, torch.linalg.LinAlgError) as err:
            raise FitError(f"jiles_atherton: {err}") from None
        ys = y[scored]
        return _checked(m, x, t, scored, "jiles_atherton", float(ys.mean()), float(ys.std()))

    return JilesAtherton(mu0=mu0).requires_grad_(False), fit


FAMILIES: dict[str, Callable[[Mapping[str, Any]], tuple[nn.Module, Fitter]]] = {
    "pi_nonneg": _pi_nonneg,
    "gpi": _gpi,
    "preisach": _preisach,
    "stop_pi": _stop_pi,
    "jiles_atherton": _jiles_atherton,
    "drift": _drift,
}
"""Builders of the family operators by config name: ``spec -> (placeholder, fitter)``."""
