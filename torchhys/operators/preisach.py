"""The Preisach operator, its per-sample step, and its identification by non-negative least
squares.

The maths (relays, tie rule, smooth relays, the chunked sequence path) is in
:mod:`torchhys.functional.preisach`; the module holds the grid, the density and the state,
and the step calls the same :func:`~torchhys.functional.preisach.relay_update` and
:func:`~torchhys.functional.preisach.relay_output` as the sequence path.

References:
    I. D. Mayergoyz, Mathematical Models of Hysteresis, Springer, 1991.
"""

from __future__ import annotations

import functools
import warnings
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_bool,
    check_nonnegative_weights,
    check_warmup,
    fitted_samples,
)
from torchhys.functional.preisach import (
    _check_smooth,
    _real,
    _relay_chunks,
    check_relay_state,
    check_scale,
    demagnetized_state,
    graded_input,
    graded_input_inverse,
    preisach_grid,
    preisach_with_state,
    relay_output,
    relay_update,
)
from torchhys.identification._nnls import (
    Moments,
    check_penalty,
    check_validation,
    fit_segments,
    nnls_gram,
    select_on_holdout,
)
from torchhys.operator import (
    Example,
    HysteresisOperator,
    OperatorStep,
    StateBlock,
    register_operator,
)

if TYPE_CHECKING:
    from torchhys.operators.preisach_inverse import PreisachInverse

__all__ = ["Preisach", "PreisachStep", "fit_preisach", "select_penalty"]


class Preisach(HysteresisOperator):
    """Discretised Preisach model ``offset + linear * x + sum_k w_k r_k[x]`` of the
    K = n (n + 1) / 2 relays of :func:`~torchhys.functional.preisach_grid` on [lo, hi].

    The density ``weights`` (K,) is stored as is, non-negative: the constructor,
    :func:`fit_preisach` and ``load_state_dict`` keep it so (loading negative weights raises
    ``ValueError``). A gradient step may take it below zero: forward uses ``max(w, 0)``, whose
    gradient passes at 0, and :meth:`project_` clamps the stored values (call it after each
    optimizer step: projected gradient). Stored rather than behind a softplus so that the
    exact zeros of a non-negative least-squares fit are representable. Initial density:
    uniform, ``1 / K`` (a major loop from -1 to 1).

    Args:
        lo, hi: input range of the grid; beyond it the relays saturate.
        n: levels per axis (>= 1).
        linear: learn a linear term ``linear * x`` (else fixed at 0).
        offset: learn an offset (else fixed at 0).
        smooth: temperature of smooth relays (gradients in x), or None for hard relays.
        initial: relays before the first sample: ``"demagnetized"`` (+1 below the line
            ``alpha + beta = lo + hi``, -1 on and above it), ``"negative"`` or ``"positive"``
            (after saturation: all -1 or all +1), or a (K,) tensor of +-1.
        scale: None (an even grid), or s > 0: a graded grid
            (:func:`~torchhys.functional.preisach_grid`), whose levels are equal steps of
            ``g(x) = c + s asinh((x - c) / s)``, c = (lo + hi) / 2: dense within about s of
            the centre, sparse beyond. The linear term then reads g(x), a reversible part
            that saturates. For a magnetic core modelled from its field (H -> B; invert it
            with :meth:`inverse` for the compensator B -> H), s about a tenth of the largest
            field puts thresholds where the small loops turn. Saved in the state dict
            (buffer ``grading``: centre, then scale or 0).

    Shape:
        - x: (time,) or (batch, time)
        - state: the relays at the last sample, (K,) or (batch, K), +-1; None: ``initial``
        - returns ``(y, state)``: y the shape of x; chunked calls equal one call.

    References:
        I. D. Mayergoyz, Mathematical Models of Hysteresis, Springer, 1991.
    """

    n_outputs: int = 1

    def __init__(
        self,
        lo: float,
        hi: float,
        n: int = 20,
        *,
        linear: bool = True,
        offset: bool = True,
        smooth: float | None = None,
        initial: str | Tensor = "demagnetized",
        scale: float | None = None,
    ) -> None:
        super().__init__()
        check_bool(linear, "linear")
        check_bool(offset, "offset")
        alpha, beta = preisach_grid(lo, hi, n, scale=scale, dtype=torch.float64)
        self.lo, self.hi, self.n, self.n_relays = float(lo), float(hi), n, alpha.numel()
        self.smooth = _check_smooth(smooth)
        self.centre, self.scale = 0.5 * (self.lo + self.hi), check_scale(scale)
        dtype = torch.get_default_dtype()
        # (centre, scale) of the grading, scale 0 for none: saved with the model
        self.register_buffer("grading", torch.tensor(
            [self.centre, 0.0 if self.scale is None else self.scale], dtype=dtype))
        self._read_grading()
        self.register_buffer("initial_relays", self._initial(initial, alpha, beta).to(dtype))
        self.register_buffer("alpha", alpha.to(dtype))
        self.register_buffer("beta", beta.to(dtype))
        self.weights = nn.Parameter(torch.full_like(self.alpha, 1.0 / self.n_relays))
        for name, learn in (("linear", linear), ("offset", offset)):
            if learn:
                setattr(self, name, nn.Parameter(torch.zeros(())))
            else:
                self.register_buffer(name, torch.zeros(()))

    def _initial(self, initial: str | Tensor, alpha: Tensor, beta: Tensor) -> Tensor:
        choices = ("demagnetized", "negative", "positive")
        if isinstance(initial, Tensor):
            if initial.shape != alpha.shape:
                raise ValueError(f"initial must be one of {choices} or a tensor of shape "
                                 f"({alpha.numel()},) of +-1, got shape {tuple(initial.shape)}")
            if not bool(((initial == 1) | (initial == -1)).all()):
                raise ValueError("initial must hold relay values +-1, got values "
                                 f"{sorted(set(initial.tolist()))[:5]}")
            return initial.to(alpha.dtype).clone()
        if initial == "demagnetized":
            return demagnetized_state(alpha, beta, 0.5 * (self.lo + self.hi))
        if initial in ("negative", "positive"):
            return torch.full_like(alpha, -1.0 if initial == "negative" else 1.0)
        raise ValueError(f"initial must be one of {choices} or a tensor, got {initial!r}")

    def _read_grading(self) -> None:
        """The grading as Python numbers, from the saved buffer (in its dtype's rounding, so
        that a loaded copy computes the same)."""
        self.centre = float(self.grading[0])
        self.scale = float(self.grading[1]) if float(self.grading[1]) > 0 else None

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        check_relay_state(state, x, self.alpha.shape[0], "state")
        r0 = self.initial_relays if state is None else state
        return preisach_with_state(
            x, self.weights.clamp_min(0.0), self.alpha, self.beta, offset=self.offset,
            linear=self.linear, r0=r0, smooth=self.smooth, centre=self.centre,
            scale=self.scale,
        )

    @torch.no_grad()
    def project_(self) -> Preisach:
        """Clamp the stored density at 0 (after an optimizer step); returns self."""
        self.weights.clamp_(min=0.0)
        return self

    def streaming_step(self, dtype: torch.dtype) -> PreisachStep:
        """The per-sample step with the current parameters (detached), in ``dtype``."""
        return PreisachStep(self.alpha, self.beta, self.weights.clamp_min(0.0), self.linear,
                            self.offset, self.initial_relays, self.smooth, dtype,
                            self.centre, self.scale)

    def inverse(self) -> PreisachInverse:
        """The exact inverse ``x = F^-1[y]`` as an operator (:class:`~torchhys.PreisachInverse`,
        detached parameters; see :mod:`torchhys.operators.preisach_inverse`): the compensator of
        this
        model. It shares the model's state (the relays).

        Raises:
            ValueError: smooth relays, or an output that does not rise strictly with the
                input (``linear`` not > 0).
        """
        from torchhys.operators.preisach_inverse import PreisachInverse

        return PreisachInverse.from_model(self)

    def extra_repr(self) -> str:
        graded = "" if self.scale is None else f", scale={self.scale:.6g}"
        return f"lo={self.lo}, hi={self.hi}, n={self.n}, smooth={self.smooth}{graded}"

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[override]
        w = state_dict.get(prefix + "weights")
        if isinstance(w, Tensor):
            check_nonnegative_weights(w, prefix + "weights", "non-negative (a Preisach density)")
        a, b, r, g = (state_dict.get(prefix + k) for k in ("alpha", "beta", "initial_relays",
                                                             "grading"))
        check_saved_grid(prefix, *(v if isinstance(v, Tensor) else None for v in (a, b, r, g)))
        if g is None and isinstance(a, Tensor):  # saved before graded grids: an even grid
            state_dict[prefix + "grading"] = torch.tensor(
                [0.5 * float(a.max() + a.min()), 0.0], dtype=self.grading.dtype)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        self._read_grading()
        if isinstance(a, Tensor) and a.shape == self.alpha.shape and self.n > 1:
            # the grid range of the loaded thresholds (cell centres, module docstring),
            # in the graded variable where the cells are equal
            c, s = self.centre, self.scale
            gl, gh = (graded_input(torch.stack([a.min(), a.max()]).double().cpu(), c, s)
                      .tolist())
            half = 0.5 * (gh - gl) / (self.n - 1)
            self.lo, self.hi = graded_input_inverse(
                torch.tensor([gl - half, gh + half], dtype=torch.float64), c, s).tolist()


def check_saved_grid(prefix: str, alpha: Tensor | None, beta: Tensor | None,
                     initial: Tensor | None, grading: Tensor | None) -> None:
    """The values of a Preisach grid about to be loaded (each None where not given): finite
    thresholds ``alpha >= beta`` (when both are given, of one shape), initial relays of +-1,
    and a grading ``(centre, scale)``, finite, scale >= 0.

    Raises:
        ValueError: naming the key (after ``prefix``).
    """
    if alpha is not None and beta is not None and alpha.shape == beta.shape and not bool(
            (alpha.isfinite() & beta.isfinite() & (alpha >= beta)).all()):
        raise ValueError(f"{prefix}alpha and {prefix}beta must be finite thresholds with "
                         "alpha >= beta (a Preisach grid)")
    if initial is not None and not bool(((initial == 1) | (initial == -1)).all()):
        raise ValueError(f"{prefix}initial_relays must hold relay values +-1")
    if grading is not None and (grading.shape != (2,) or not bool(grading.isfinite().all())
                                or float(grading[1]) < 0):
        raise ValueError(f"{prefix}grading must be (centre, scale), finite, scale >= 0 "
                         f"(0: an even grid), got {grading.tolist()!r:.80}")


class PreisachStep(OperatorStep):
    """Per-sample step of :class:`Preisach`: ``r = relay_update(x, alpha, beta, r_prev)``,
    features ``offset + linear * x + relay_output(x, ..., r) @ w``.

    State: one block ``"relays"`` (batch, K), starting at the initial relays. Shapes: x
    (batch, 1) -> features (batch, 1). Written for TorchScript and ``torch.export``.
    """

    def __init__(self, alpha: Tensor, beta: Tensor, weights: Tensor, linear: Tensor,
                 offset: Tensor, initial: Tensor, smooth: float | None,
                 dtype: torch.dtype, centre: float = 0.0, scale: float | None = None) -> None:
        super().__init__()
        self.n_outputs = 1
        self.state_spec = [StateBlock("relays", alpha.numel(), start=initial.tolist())]
        self.smooth = smooth
        self.centre, self.scale = float(centre), scale
        for name, v in (("alpha", alpha), ("beta", beta), ("weights", weights[:, None]),
                        ("linear", linear), ("offset", offset)):
            self.register_buffer(name, v.detach().to(dtype).clone())

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        r = relay_update(x, self.alpha, self.beta, state[0])
        out = relay_output(x, self.alpha, self.beta, r, self.smooth)
        lin = self.linear * graded_input(x, self.centre, self.scale)
        return self.offset + lin + out @ self.weights, [r]


def fit_preisach(
    x: Tensor,
    y: Tensor,
    *,
    lo: float | None = None,
    hi: float | None = None,
    n: int = 20,
    ridge: float = 0.0,
    smoothness: float = 0.0,
    linear: bool = True,
    warmup: int = 0,
    scale: float | None = None,
    mask: Tensor | None = None,
) -> Preisach:
    """Identify a :class:`Preisach` model (demagnetised start, hard relays) by penalised
    non-negative least squares of the density, with a free offset and linear term:

        min  mean_t (y[t] - offset - linear x[t] - r[t] @ w)**2
             + ridge * |w|**2 + smoothness * |D w|**2        subject to w >= 0,

    D the differences between neighbouring relays of the grid (alpha or beta one level
    apart). Solved in float64 from the normal equations (accumulated chunk by chunk) with the
    Lawson-Hanson active-set method, the free variables always in the passive set.

    Args:
        x, y: input and output, (time,) or (batch, time) (each row starts demagnetised).
        lo, hi: grid range; default the range of x. Samples outside saturate the relays
            (one warning gives their share; with a ``mask``, of the masked samples).
        n: levels per axis; ridge, smoothness: penalties (>= 0); linear: fit the linear term.
        warmup: samples at the start of each row left out of the fit (their relays still
            run), to forget the assumed initial state.
        scale: None (an even grid), or a graded grid's scale (:class:`Preisach`).
        mask: the samples to fit, bool, the shape of ``x`` (False: left out of the fit, the
            relays still run through them, e.g. a held-out block or a shorter row's
            padding); None: every sample (after ``warmup`` in both cases).

    Returns:
        The fitted model, in x's dtype.

    Raises:
        ValueError: NaN/inf in x or y, shapes differ, a bad grid, warmup >= time, a negative
            penalty.

    Warns:
        RuntimeWarning: once, with the share of samples of x outside [lo, hi].
    """
    xb, yb, model, samples = _prepare(x, y, lo, hi, n, linear, warmup, None, scale, mask)
    (G, h, _, count), = _normal_equations(xb, yb, model, samples)
    theta = _solve(G / count, h / count, model, check_penalty(ridge, "ridge"),
                   check_penalty(smoothness, "smoothness"))
    return _set(model, theta)


def select_penalty(
    x: Tensor,
    y: Tensor,
    penalties: list[float],
    *,
    kind: str = "smoothness",
    validation: float = 0.25,
    lo: float | None = None,
    hi: float | None = None,
    n: int = 20,
    linear: bool = True,
    warmup: int = 0,
    scale: float | None = None,
    mask: Tensor | None = None,
) -> tuple[float, dict[float, float]]:
    """Choose the ``kind`` penalty (``"ridge"`` or ``"smoothness"``, the other 0) of
    :func:`fit_preisach` on a time-ordered hold-out: fit on the first ``1 - validation`` of
    each row (after ``warmup``; with a ``mask``, of its masked samples), score the RMS error
    on the rest (the relays run through the whole sequence).

    Returns:
        The penalty with the least validation RMS error (the first on ties), and the RMS
        error of each. Refit on all samples with ``fit_preisach(..., smoothness=best)``
        (or ``ridge=best``).
    """
    if kind not in ("ridge", "smoothness"):
        raise ValueError(f"kind must be one of ('ridge', 'smoothness'), got {kind!r}")
    xb, yb, model, samples = _prepare(x, y, lo, hi, n, linear, warmup,
                                      check_validation(validation), scale, mask)
    train, valid = _normal_equations(xb, yb, model, samples)

    last: Tensor | None = None  # each penalty's fit starts from the previous one's solution

    def solve(G: Tensor, h: Tensor, p: float) -> Tensor:
        nonlocal last
        last = _solve(G, h, model, *((p, 0.0) if kind == "ridge" else (0.0, p)), init=last)
        return last

    return select_on_holdout(train, valid, penalties, solve)


def _prepare(x: Tensor, y: Tensor, lo: float | None, hi: float | None, n: int, linear: bool,
             warmup: int, validation: float | None, scale: float | None,
             mask: Tensor | None) -> tuple[Tensor, Tensor, Preisach, list[Tensor]]:
    """Check the data, warn about samples outside [lo, hi]; the model and the samples of
    each segment (:func:`~torchhys.identification._nnls.fit_segments`)."""
    xb, _ = as_batched_sequence(x, "x")
    yb, _ = as_batched_sequence(y, "y")
    if xb.shape != yb.shape:
        raise ValueError(f"x and y must have the same shape, got {tuple(x.shape)} and "
                         f"{tuple(y.shape)}")
    T = xb.shape[1]
    check_warmup(warmup, T)
    if lo is None and hi is None and not float(xb.max()) > float(xb.min()):
        raise ValueError(f"x is constant ({float(xb.min()):.6g}): its range gives no grid; "
                         "give lo and hi")
    lo = float(xb.min()) if lo is None else _real(lo, "lo")
    hi = float(xb.max()) if hi is None else _real(hi, "hi")
    model = Preisach(lo, hi, n, linear=linear, scale=scale).to(xb.dtype)
    samples = fit_segments(tuple(xb.shape), warmup, mask, validation)
    xs = xb if mask is None else xb[fitted_samples(mask, tuple(xb.shape), 0).to(xb.device)]
    outside = float(((xs < lo) | (xs > hi)).double().mean())
    if outside > 0:
        where = "samples" if mask is None else "masked samples"
        warnings.warn(f"{outside:.2%} of the {where} of x lie outside [lo, hi] = [{lo:.6g}, "
                      f"{hi:.6g}]: the relays saturate there", RuntimeWarning, stacklevel=3)
    return xb, yb, model, samples


def _normal_equations(x: Tensor, y: Tensor, model: Preisach,
                      samples: list[Tensor]) -> list[Moments]:
    """The :class:`~torchhys.identification._nnls.Moments` ``(A'A, A'y, y'y, rows)`` in float64 of
    the
    design ``A = [relays, x, 1]`` over the samples of each segment (a (rows, time) bool
    mask)."""
    K, m = model.n_relays, model.n_relays + 1 + isinstance(model.linear, nn.Parameter)
    out = [[x.new_zeros(m, m, dtype=torch.float64), x.new_zeros(m, dtype=torch.float64),
            x.new_zeros((), dtype=torch.float64), 0] for _ in samples]
    r0 = model.initial_relays.to(torch.float64).expand(x.shape[0], K)
    for start, stop, r in _relay_chunks(x, model.alpha, model.beta, r0):
        for seg, mask in zip(out, samples, strict=True):
            chunk = mask[:, start:stop].to(x.device)
            if not bool(chunk.any()):
                continue
            xs = graded_input(x[:, start:stop][chunk].unsqueeze(0).to(torch.float64),
                              model.centre, model.scale)
            cols = [r[:, chunk]]
            cols += [xs] if m > K + 1 else []
            A = torch.cat(cols + [torch.ones_like(xs)])
            ys = y[:, start:stop][chunk].to(torch.float64)
            seg[0] += A @ A.T
            seg[1] += A @ ys
            seg[2] += ys @ ys
            seg[3] += ys.numel()
    return [Moments(*seg) for seg in out]


@functools.lru_cache(maxsize=8)
def _difference_gram(n: int) -> Tensor:
    """``D'D`` (K, K), float64, of the first differences D of the density between
    neighbouring relays of an n-level grid (along alpha and along beta); read only."""
    K = n * (n + 1) // 2
    i, j = torch.tril_indices(n, n)
    k = torch.arange(K)
    pairs = [(k[i < n - 1], (i * (i + 1) // 2 + i + 1 + j)[i < n - 1]), (k[j < i], k[j < i] + 1)]
    first = torch.cat([p[0] for p in pairs])
    second = torch.cat([p[1] for p in pairs])
    D = torch.zeros(first.numel(), K, dtype=torch.float64)
    D[torch.arange(first.numel()), first] = -1.0
    D[torch.arange(first.numel()), second] = 1.0
    return D.T @ D


def _solve(G: Tensor, h: Tensor, model: Preisach, ridge: float, smoothness: float,
           init: Tensor | None = None) -> Tensor:
    """The penalised NNLS solution: density (K,), then the free linear term and offset
    (``init``: a warm start, :func:`~torchhys.identification._nnls.nnls_gram`)."""
    K, m = model.n_relays, G.shape[0]
    P = G.clone()
    P[:K, :K] += ridge * torch.eye(K, dtype=torch.float64) + smoothness * _difference_gram(model.n)
    free = torch.arange(m) >= K
    return nnls_gram(P, h, free, init)


def _set(model: Preisach, theta: Tensor) -> Preisach:
    K = model.n_relays
    with torch.no_grad():
        model.weights.copy_(theta[:K].clamp_min(0.0))
        if isinstance(model.linear, nn.Parameter):
            model.linear.copy_(theta[K])
        model.offset.copy_(theta[-1])
    return model


def _example() -> Preisach:
    """Hard relays on [-1, 1] (10 relays), an uneven density and a linear term."""
    model = Preisach(-1.0, 1.0, 4).double()
    with torch.no_grad():
        model.weights.copy_(torch.linspace(0.05, 0.2, model.n_relays))
        model.linear.fill_(0.3)
        model.offset.fill_(0.1)
    return model


register_operator("preisach", Preisach, example=Example(
    # the step sums the relays in another order than the sequence path
    _example, atol=1e-13, bad_values={"weights": -1.0, "initial_relays": 0.0}))
