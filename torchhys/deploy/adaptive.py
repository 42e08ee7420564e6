"""A compensator that adapts its readout online from the measured response:
:class:`AdaptiveCompensator`.

The inverse model's training pair is (response y, command u): its features are computed from
y and its readout predicts u. While it runs, the adaptive compensator gets at each sample the
pair of the last sample, ``measured_prev`` (the response y_{t-1} the device gave) and
``applied_prev`` (the command u_{t-1} that was applied), computes the features of the
measured response with a second copy of the steps' state, and moves the readout's weights to
predict u_{t-1} from them (:func:`~torchhys.functional.rls_update` or
:func:`~torchhys.functional.nlms_update`). The command for the desired output x_t is then the
readout with the new weights, followed by everything the static compensator does (the input
clamp, the limits, the direction guard, the hold of a non-finite sample).

What qualifies: a model whose compensator head has an affine readout
(:class:`~torchhys.protocols.AffineReadout`): :class:`~torchhys.InverseHysteresisNet` (with
an identity activation the readout is over the features themselves, else over the hidden
layer) and :class:`~torchhys.conditions.ScheduledReadout`; or one with an equal form that has
(:class:`~torchhys.protocols.AffineForm`): :class:`~torchhys.PrandtlIshlinskiiInverse` (its
plays' weights, the linear weight and a bias).

The update works in normalized regressors ``z = basis(f) / s``: ``s`` is each regressor's
root mean square over a sweep of the training input range (decaying triangles, the
conditions ramped over their range), so that the forgetting factor, the bound, the excitation
threshold and RLS's initial covariance mean the same for every model. An update is skipped
(and the weights kept) where:

- the pair is not finite (``measured_prev`` or ``applied_prev`` NaN or inf, or missing):
  counted by :meth:`AdaptiveCompensator.skipped_count`;
- the prediction error is within ``dead_zone`` (command units);
- the regressors have moved less than ``excitation`` (max-norm, normalized) since the last
  applied update (a still period: RLS's covariance cannot wind up over it);
- with a direction guard: the update would make the readout's change between the last
  update's measured response and this one go against the device's direction (counted by
  :meth:`AdaptiveCompensator.refused_count`).

An applied update keeps each normalized weight within ``adapt_bound`` times
``max(|w0_i|, rms(w0))`` of the offline fit's ``w0``; RLS's covariance is kept at a trace of
at most its initial one, and reset to the initial one where it lost positive diagonal.

State (the static layout's tensors first, all zeros when fresh, see
:mod:`torchhys.deploy.streaming`)::

    index   name    dtype    shape            columns
    0..k-1  ...     ...      ...              the desired path: the static compensator's state
    k..2k-1 ...     ...      ...              the measured path: the same layout on y
    2k      W       real     (batch, m)       weights - offline weights (normalized)
    2k+1    P       real     (batch, m*m)     RLS only: covariance - initial covariance
    next    Z       real     (batch, m+1)     the last update's regressors and clamped y
    next    A       int64    (batch, 3)       [updates applied, pairs skipped (not finite),
                                              updates refused (direction)]

(``k`` is 3, or 4 with a float64 block.)
"""


import math
from collections.abc import Sequence
from typing import Final

import torch
from torch import Tensor, nn

from torchhys._checks import check_choice, check_real
from torchhys.deploy._slots import conditions_of
from torchhys.deploy.ranges import RANGES, default_input_range
from torchhys.deploy.streaming import _ADAPTIVE, StreamingCompensator
from torchhys.functional.adaptive import nlms_update, rls_update
from torchhys.protocols import AffineForm, check_readout
from torchhys.step import OperatorStep

__all__ = ["ADAPT_METHODS", "AdaptiveCompensator"]

#: the update rules of ``adapt``
ADAPT_METHODS = ("rls", "nlms")


def _check_fraction(value: object, name: str, low_open: bool) -> float:
    v = check_real(value, name)
    if not (0.0 < v <= 1.0) if low_open else not (0.0 <= v <= 1.0):
        raise ValueError(f"{name} must be in {'(0' if low_open else '[0'}, 1], got {v!r}")
    return v


def _check_nonnegative(value: object, name: str) -> float:
    v = check_real(value, name)
    if not (v >= 0.0 and math.isfinite(v)):
        raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    return v


class _AffineModel(nn.Module):
    """A model of :class:`~torchhys.protocols.AffineForm` streamed in that form (its
    recorded ranges copied)."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model
        for name in RANGES:
            value = getattr(model, name, None)
            if isinstance(value, Tensor):
                self.register_buffer(name, value.detach().clone())

    def streaming_steps(self, dtype: torch.dtype) -> list[OperatorStep]:
        return self.model.affine_form(dtype)[0]

    def streaming_head(self, dtype: torch.dtype) -> nn.Module:
        return self.model.affine_form(dtype)[1]


class AdaptiveCompensator(StreamingCompensator):
    """A streaming compensator whose readout adapts online (module docstring).

    Args:
        model: a trained model whose head has an affine readout
            (:class:`~torchhys.protocols.AffineReadout`).
        adapt: ``"rls"`` (recursive least squares with forgetting; state O(m^2)) or
            ``"nlms"`` (normalized LMS; state O(m), for small microcontrollers).
        forgetting: RLS's forgetting factor in (0, 1] (per applied update).
        adapt_bound: the weights' box around the offline fit, as a share of their scale
            (>= 0; 0 freezes them).
        dead_zone: no update while ``|error| <= dead_zone`` (command units, >= 0).
        excitation: no update until the normalized regressors moved by more than this
            since the last update (>= 0).
        nlms_step: NLMS's step size in (0, 1].
        initial_covariance: RLS's initial covariance ``p0 I`` of the normalized weights
            (> 0): larger moves faster from the offline fit.
        limits, initial_command, input_range, input_margin, direction, condition_ranges:
            as :class:`~torchhys.deploy.streaming.StreamingCompensator`.

    Methods: as the static compensator's, with ``step(x_t, conditions=None,
    measured_prev=None, applied_prev=None)``, ``forward(x, conditions=None, measured=None,
    applied=None)`` and ``step_explicit(x, state, conditions=None, measured_prev=None,
    applied_prev=None)``; ``adapted_weights()`` (batch, m) and ``offline_weights()`` (m,) in
    the readout's units; ``updates_count()``, ``skipped_count()``, ``refused_count()``
    (batch,) long. ``reset()`` returns to the offline weights.

    Raises:
        ValueError: a model without an affine readout; a bad ``adapt``, ``forgetting``,
            ``adapt_bound``, ``dead_zone``, ``excitation``, ``nlms_step`` or
            ``initial_covariance`` (the message names it); see the static compensator.
    """

    rls: Final[bool]
    forgetting: Final[float]
    dead_zone: Final[float]
    excitation: Final[float]
    nlms_step: Final[float]
    m: Final[int]
    k: Final[int]
    trace_max: Final[float]
    p0: Final[float]

    def __init__(
        self, model: nn.Module, *, adapt: str = "rls", forgetting: float = 0.995,
        adapt_bound: float = 0.5, dead_zone: float = 0.0, excitation: float = 1e-3,
        nlms_step: float = 0.2, initial_covariance: float = 1.0,
        limits: Sequence[float] | None = None, initial_command: float = 0.0,
        input_range: Sequence[float] | None = None, input_margin: float | None = 0.05,
        direction: str = "auto", condition_ranges: Sequence[Sequence[float]] | None = None,
    ) -> None:
        check_choice(adapt, "adapt", list(ADAPT_METHODS))
        forgetting = _check_fraction(forgetting, "forgetting", True)
        nlms_step = _check_fraction(nlms_step, "nlms_step", True)
        bound = _check_nonnegative(adapt_bound, "adapt_bound")
        dead = _check_nonnegative(dead_zone, "dead_zone")
        excitation = _check_nonnegative(excitation, "excitation")
        p0 = check_real(initial_covariance, "initial_covariance")
        if not (p0 > 0.0 and math.isfinite(p0)):
            raise ValueError(f"initial_covariance must be a finite number > 0, got {p0!r}")
        if isinstance(model, AffineForm) and not isinstance(model, StreamingCompensator):
            model = _AffineModel(model)
        super().__init__(model, limits=limits, initial_command=initial_command,
                         input_range=input_range, input_margin=input_margin,
                         direction=direction, condition_ranges=condition_ranges)
        check_readout(self.head, "model")
        self.rls, self.forgetting, self.dead_zone = adapt == "rls", forgetting, dead
        self.excitation, self.nlms_step, self.p0 = excitation, nlms_step, p0
        dtype = self.low.dtype
        with torch.no_grad():
            w0 = self.head.readout_weights().double()
            sweep = (default_input_range(model) if input_range is None
                     else (float(input_range[0]), float(input_range[1])))
            scale = self._regressor_scale(w0.numel(), sweep)
            wn = w0 * scale  # the offline weights of the normalized regressors
        self.m = int(w0.numel())
        self.trace_max = p0 * self.m
        rms = float(wn.square().mean().sqrt())
        self.register_buffer("inv_scale", (1.0 / scale).to(dtype))
        self.register_buffer("w0", wn.to(dtype))
        self.register_buffer("bound", (bound * torch.clamp(wn.abs(), min=rms)).to(dtype))
        eye = torch.eye(self.m, dtype=torch.float64)
        self.register_buffer("p_init", (p0 * eye).to(dtype))
        self.k = len(self.templates)
        base = [t.clone() for t in self.templates]
        extra = [torch.zeros(1, self.m, dtype=dtype)]
        names = ["W (weights - offline weights)"]
        if self.rls:
            extra.append(torch.zeros(1, self.m * self.m, dtype=dtype))
            names.append("P (covariance - initial covariance)")
        extra += [torch.zeros(1, self.m + 1, dtype=dtype), torch.zeros(1, 3, dtype=torch.long)]
        names += ["Z (the last update's regressors and clamped y)",
                  "A (updates applied, pairs skipped, updates refused)"]
        self.templates = base + [t.clone() for t in base] + extra
        self.state_names = ([n for n in self.state_names[:self.k]]
                            + ["measured " + n for n in self.state_names[:self.k]] + names)
        self.state = self.initial_state(1)

    def _regressor_scale(self, m: int, sweep: tuple[float, float] | None) -> Tensor:
        """Each regressor's root mean square (float64, (m,)) over a sweep of the training
        input range (the module docstring); ones without a range, or where a regressor is
        0 over the sweep."""
        if sweep is None or not (math.isfinite(sweep[0]) and math.isfinite(sweep[1])
                                 and sweep[1] > sweep[0]):
            return torch.ones(m, dtype=torch.float64)
        lo, hi = sweep
        t = torch.linspace(0.0, 1.0, 2000, dtype=torch.float64)
        amp = 1.0 - 0.8 * t  # decaying triangles about the middle of the range
        tri = 2.0 * torch.abs(torch.remainder(t * 6.0, 1.0) - 0.5)  # 0..1
        x = (0.5 * (lo + hi) + (tri - 0.5) * amp * (hi - lo)).to(self.low.dtype)
        n = self.n_conditions
        c = x.new_zeros([0])
        if n > 0:
            clo, chi = self.cond_low.double(), self.cond_high.double()
            ok = torch.isfinite(clo) & torch.isfinite(chi)
            clo, chi = torch.where(ok, clo, 0.0), torch.where(ok, chi, 0.0)
            c = (clo + t.unsqueeze(1) * (chi - clo)).to(self.low.dtype)
        state = self.initial_state(1)
        rows = []
        for i in range(t.numel()):
            ci = c[i].unsqueeze(0) if n > 0 else c
            f, new, xc, cc = self._features(x[i:i + 1], state, ci)
            rows.append(self.head.readout_basis(f).double())
            _, state = self._finish(x[i:i + 1], state, ci, self.head(f), new, xc, cc)
        rms = torch.cat(rows, 0).square().mean(0).sqrt()
        return torch.where(rms > 1e-12 * float(rms.max()), rms, torch.ones_like(rms))

    def example_inputs(self, batch: int) -> list[tuple[str, Tensor]]:
        """The static compensator's, then ``measured_prev`` and ``applied_prev`` (batch,)."""
        pair = [(name, torch.zeros(batch, dtype=self.low.dtype))
                for name in ("measured_prev", "applied_prev")]
        return super().example_inputs(batch) + pair

    def _step_inputs(self, x_t: Tensor, conditions: Tensor | None) -> Tensor:
        return conditions if conditions is not None else x_t.new_zeros([0])

    def _inputs(self, x: Tensor, conditions: Tensor | None, measured: Tensor | None,
                applied: Tensor | None, where: str) -> Tensor:
        """``[conditions..., measured, applied]`` (x's shape + (n + 2,)), NaN where a
        pair's member is missing (no update)."""
        c = conditions_of(x, conditions, self.n_conditions, self.low.dtype, where, x.dim() + 1)
        cols = [c] if self.n_conditions > 0 else []
        return torch.cat(cols + [self._member(x, measured, "measured_prev", where),
                                 self._member(x, applied, "applied_prev", where)], -1)

    def _member(self, x: Tensor, value: Tensor | None, name: str, where: str) -> Tensor:
        if value is None:
            return torch.full_like(x, math.nan, dtype=self.low.dtype).unsqueeze(-1)
        if list(value.shape) != list(x.shape):
            raise ValueError(where + ": " + name + " must have x's shape " + str(list(x.shape))
                             + ", got " + str(list(value.shape)))
        return value.to(self.low.dtype).unsqueeze(-1)

    @torch.jit.export
    def step(self, x_t: Tensor, conditions: Tensor | None = None,
             measured_prev: Tensor | None = None, applied_prev: Tensor | None = None
             ) -> Tensor:
        """Advance by one sample: x_t (batch,) the desired output, ``measured_prev`` and
        ``applied_prev`` (batch,) the last sample's response and applied command (None:
        no pair this sample, no update) -> command (batch,)."""
        if x_t.dim() != 1:
            raise ValueError(
                "step expects one sample per row, shape (batch,), got shape " + str(x_t.shape))
        inputs = self._inputs(x_t, conditions, measured_prev, applied_prev, "step")
        if torch.jit.is_scripting():
            return self._step(x_t, inputs)
        return self._locked(x_t, True, inputs)

    @torch.jit.export
    def step_explicit(self, x: Tensor, state: list[Tensor], conditions: Tensor | None = None,
                      measured_prev: Tensor | None = None, applied_prev: Tensor | None = None
                      ) -> tuple[Tensor, list[Tensor]]:
        """:meth:`step` with the state passed explicitly (the module docstring's layout)."""
        self._check_state(x, state)
        return self._advance(x, state, self._inputs(x, conditions, measured_prev,
                                                    applied_prev, "step_explicit"))

    def forward(self, x: Tensor, conditions: Tensor | None = None,
                measured: Tensor | None = None, applied: Tensor | None = None) -> Tensor:
        """Commands for a sequence from a fresh state: x (time,) or (batch, time); at
        sample t the pair is ``measured[..., t]``, ``applied[..., t]`` (the previous
        sample's response and command; None: no updates)."""
        if x.dim() not in (1, 2):
            raise ValueError(
                "x must have shape (time,) or (batch, time), got shape " + str(x.shape))
        inputs = self._inputs(x, conditions, measured, applied, "forward")
        xb = x.to(self.low.dtype)
        if x.dim() == 1:
            xb, inputs = xb.unsqueeze(0), inputs.unsqueeze(0)
        state = self.initial_state(xb.shape[0])
        outs: list[Tensor] = []
        for t, xt in enumerate(xb.unbind(1)):
            u, state = self._advance(xt, state, inputs[:, t])
            outs.append(u)
        if len(outs) == 0:
            return x.to(self.low.dtype)
        y = torch.stack(outs, dim=1)
        return y[0] if x.dim() == 1 else y

    def _advance(self, x: Tensor, state: list[Tensor],
                 inputs: Tensor) -> tuple[Tensor, list[Tensor]]:
        """One adaptive sample of a state of the layout; ``inputs`` (batch, n + 2)."""
        n, k, m = self.n_conditions, self.k, self.m
        c = inputs[:, :n]
        y, target = inputs[:, n], inputs[:, n + 1]
        desired, measured = state[:k], state[k:2 * k]
        i = 2 * k
        W = state[i]
        Z, A = state[len(state) - 2], state[len(state) - 1]
        # the measured path: its features, its state held on a non-finite y
        fm, new_m, yc, ccm = self._features(y, measured, c)
        z = self.head.readout_basis(fm) * self.inv_scale
        w = self.w0 + W
        pred = (z * w).sum(1, keepdim=True)
        _, measured_new = self._finish(y, measured, c, pred, new_m, yc, ccm)
        had = measured[self.STATE_STARTED].squeeze(1)  # a pair before this one
        z_last = Z.narrow(1, 0, m)
        P = state[i + 1]  # RLS's covariance (NLMS: the next tensor, used by no output)
        P_new = P
        if self.rls:
            w_new, P_full, ok = rls_update(
                w, self.p_init + P.view(-1, m, m), z, z_last, target, self.w0, self.bound,
                self.forgetting, self.dead_zone, self.excitation, self.trace_max)
            # a covariance that lost its positive diagonal (rounding) restarts from p0 I
            # (the diagonal alone: from a finite P, a non-finite element of the update makes
            # its row's or column's diagonal element non-finite or not positive)
            diag = torch.diagonal(P_full, 0, 1, 2)
            lost = ((diag <= self.zero) | ((diag - diag) != self.zero)).any(1)
            P_new = torch.where(lost.view(-1, 1, 1), self.p_init, P_full).flatten(1) - (
                self.p_init.flatten().unsqueeze(0))
        else:
            w_new, ok = nlms_update(w, z, z_last, target, self.w0, self.bound, self.nlms_step,
                                    1e-6, self.dead_zone, self.excitation)
        finite_pair = ((y - y) + (target - target)) == self.zero
        ok = ok & had & finite_pair  # an infinite y is clamped: its regressors are finite
        if self.guard:  # the readout's change must go the device's way
            dy = yc.squeeze(1) - Z.narrow(1, m, 1).squeeze(1)
            du = ((z - z_last) * w_new).sum(1)
            refused = ok & (du * dy * self.direction < self.zero)
        else:
            refused = torch.zeros_like(ok)
        applied = ok & ~refused
        first = finite_pair & ~had
        a2 = applied.unsqueeze(1)
        W_out = torch.where(a2, w_new - self.w0, W)
        Z_out = torch.where(a2 | first.unsqueeze(1), torch.cat([z, yc], 1), Z)
        counts = torch.stack([applied, ~finite_pair, refused], 1).to(A.dtype)
        A_out = A + counts
        # the desired path with the new weights
        fd, new_d, xc, cc = self._features(x, desired, c)
        zd = self.head.readout_basis(fd) * self.inv_scale
        u = (zd * (self.w0 + W_out)).sum(1, keepdim=True)
        u_out, desired_new = self._finish(x, desired, c, u, new_d, xc, cc)
        extra = [W_out]
        if self.rls:
            extra.append(torch.where(a2, P_new, P))
        return u_out, desired_new + measured_new + extra + [Z_out, A_out]

    @torch.jit.export
    def adapted_weights(self) -> Tensor:
        """The readout's current weights (batch, m), in the units of
        ``head.readout_weights()`` (the offline fit's after a reset)."""
        return (self.w0 + self.state[2 * self.k]) * self.inv_scale

    @torch.jit.export
    def offline_weights(self) -> Tensor:
        """The offline fit's readout weights (m,)."""
        return self.w0 * self.inv_scale

    def _count(self, column: int) -> Tensor:
        return self.state[len(self.state) - 1][:, column]

    @torch.jit.export
    def updates_count(self) -> Tensor:
        """Updates applied, per row (batch,)."""
        return self._count(0)

    @torch.jit.export
    def skipped_count(self) -> Tensor:
        """Pairs skipped because the measured response or the applied command was missing,
        NaN or inf, per row (batch,)."""
        return self._count(1)

    @torch.jit.export
    def refused_count(self) -> Tensor:
        """Updates refused because they would turn the readout against the device's
        direction, per row (batch,)."""
        return self._count(2)


# TorchScript reads a module's constants and attribute types from its class's own
# annotations: the static compensator's are the adaptive one's too
AdaptiveCompensator.__annotations__ = {**StreamingCompensator.__annotations__,
                                       **AdaptiveCompensator.__annotations__}
_ADAPTIVE.append(AdaptiveCompensator)  # StreamingCompensator(..., adapt=...) builds it
