"""Deterministic input signals for exciting and testing hysteretic systems.

Convention: every generator takes a time vector ``t`` of shape ``(time,)`` (any floating
dtype, strictly increasing not required) and returns the signal ``x`` of the same shape,
dtype and device. Build ``t`` with :func:`time_grid`. Angular frequencies are in rad/s, as
in the paper (``4 sin(0.5 t) + 2 sin(3 t)``). Values are computed in float64 and cast back
to ``t.dtype``. Random choices (multisine phases) use a local, seeded ``torch.Generator``,
never the global random state, so equal seeds give bit-identical signals.

Autograd: the generators are meant as data and are not differentiated in their options;
:func:`to_range` and :func:`exponential_decay` are differentiable in ``x``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from torchhys._checks import check_choice, check_int

__all__ = [
    "chirp",
    "decaying_sine",
    "exponential_decay",
    "multisine",
    "nested_reversals",
    "sum_of_sines",
    "time_grid",
    "to_range",
]

_SWEEPS = ("linear", "logarithmic")
_PHASES = ("random", "schroeder")


def _finite(name: str, value: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}: {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    return float(value)


def _check_t(t: Tensor) -> Tensor:
    if not isinstance(t, Tensor):
        raise TypeError(f"t must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != 1 or t.numel() == 0:
        raise ValueError(f"t must have shape (time,) with time >= 1, got shape {tuple(t.shape)}")
    if not t.is_floating_point():
        raise TypeError(f"t must have a floating dtype, got {t.dtype}")
    if not torch.isfinite(t).all():
        raise ValueError("t must be finite, got NaN or inf values")
    return t.to(torch.float64)


def _reals(name: str, values: Sequence[float], *, nonnegative: bool) -> list[float]:
    if isinstance(values, (str, bytes)) or not isinstance(values, Sequence):
        raise TypeError(f"{name} must be a sequence of numbers, got {type(values).__name__}")
    if len(values) == 0:
        raise ValueError(f"{name} must not be empty")
    out = [_finite(f"{name}[{i}]", v) for i, v in enumerate(values)]
    if nonnegative and min(out) < 0:
        raise ValueError(f"{name} must be non-negative, got {values!r}")
    return out


def time_grid(
    *,
    dt: float,
    t_end: float,
    t_start: float = 0.0,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Uniform time vector ``t_start, t_start + dt, ...`` on the half-open ``[t_start, t_end)``.

    ``time_grid(dt=0.01, t_end=8 * math.pi)`` gives the paper's 2514 samples.

    Args:
        dt: Sampling step in s, > 0.
        t_end: End time in s (excluded), > t_start.
        t_start: Start time in s.
        dtype: Floating dtype of the result; None: ``torch.get_default_dtype()``.
        device: Device of the result.

    Returns:
        t: ``(time,)``.

    Raises:
        ValueError: Non-positive ``dt``, ``t_end <= t_start``, non-finite values.
        TypeError: Non-numeric options or a non-floating ``dtype``.
    """
    dt, t_end, t_start = _finite("dt", dt), _finite("t_end", t_end), _finite("t_start", t_start)
    if dt <= 0:
        raise ValueError(f"dt must be > 0, got {dt}")
    if t_end <= t_start:
        raise ValueError(f"t_end must be > t_start = {t_start}, got {t_end}")
    if dtype is None:
        dtype = torch.get_default_dtype()
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating torch.dtype, got {dtype}")
    count = math.ceil(round((t_end - t_start) / dt, 9))
    steps = torch.arange(count, dtype=torch.float64, device=device)
    return (t_start + dt * steps).to(dtype)


def sum_of_sines(
    t: Tensor,
    *,
    amplitudes: Sequence[float] = (4.0, 2.0),
    frequencies: Sequence[float] = (0.5, 3.0),
    phases: Sequence[float] | None = None,
) -> Tensor:
    """Sum of sines ``x(t) = sum_k a_k sin(w_k t + phi_k)``.

    The default is the paper's input ``x(t) = 4 sin(0.5 t) + 2 sin(3 t)``.

    Args:
        t: Time in s, ``(time,)``.
        amplitudes: ``a_k >= 0``.
        frequencies: Angular frequencies ``w_k >= 0`` in rad/s, same length as ``amplitudes``.
        phases: ``phi_k`` in rad (default all zero), same length.

    Returns:
        x: ``(time,)``, dtype and device of ``t``.

    Raises:
        ValueError: Mismatched lengths, negative or non-finite values, bad ``t``.
        TypeError: ``t`` not a floating tensor, options not sequences of numbers.
    """
    t64 = _check_t(t)
    a = _reals("amplitudes", amplitudes, nonnegative=True)
    w = _reals("frequencies", frequencies, nonnegative=True)
    p = [0.0] * len(a) if phases is None else _reals("phases", phases, nonnegative=False)
    if not len(a) == len(w) == len(p):
        raise ValueError(
            "amplitudes, frequencies and phases must have equal lengths, got "
            f"{len(a)}, {len(w)}, {len(p)}"
        )
    x = torch.zeros_like(t64)
    for a_k, w_k, p_k in zip(a, w, p, strict=True):
        x = x + a_k * torch.sin(w_k * t64 + p_k)
    return x.to(t.dtype)


def multisine(
    t: Tensor,
    *,
    frequencies: Sequence[float] | None = None,
    band: tuple[float, float] | None = None,
    n_tones: int = 16,
    amplitude: float | None = None,
    rms: float | None = None,
    phases: str = "random",
    seed: int = 0,
) -> Tensor:
    """Equal-amplitude multisine ``x(t) = a sum_k sin(w_k t + phi_k)``.

    Give either explicit ``frequencies`` or a ``band = (w_low, w_high)`` filled with
    ``n_tones`` evenly spaced tones. Phases are ``"random"`` (uniform on ``[0, 2 pi)``,
    drawn from a local generator seeded with ``seed``) or ``"schroeder"``
    (``phi_k = -pi k (k - 1) / K``, low crest factor, ``seed`` unused).

    Args:
        t: Time in s, ``(time,)``.
        frequencies: Angular frequencies in rad/s, ``>= 0``.
        band: ``(w_low, w_high)`` in rad/s with ``0 <= w_low < w_high``.
        n_tones: Number of tones in ``band`` (>= 1).
        amplitude: Amplitude ``a >= 0`` of each tone (default 1 when ``rms`` is not given).
        rms: Target root-mean-square of the returned samples, ``> 0`` (instead of
            ``amplitude``).
        phases: ``"random"`` or ``"schroeder"``.
        seed: Seed of the local generator for random phases.

    Returns:
        x: ``(time,)``, dtype and device of ``t``.

    Raises:
        ValueError: Both or neither of ``frequencies``/``band``, both ``amplitude`` and
            ``rms``, an unknown ``phases``, invalid values, bad ``t``.
        TypeError: Wrong argument types.
    """
    t64 = _check_t(t)
    if (frequencies is None) == (band is None):
        raise ValueError("give exactly one of frequencies or band, got "
                         f"frequencies={frequencies!r}, band={band!r}")
    if band is not None:
        edges = _reals("band", band, nonnegative=True)
        if len(edges) != 2 or not edges[0] < edges[1]:
            raise ValueError(f"band must be (w_low, w_high) with w_low < w_high, got {band!r}")
        lo, hi = edges
        check_int(n_tones, "n_tones", minimum=1)
        w = torch.linspace(lo, hi, n_tones, dtype=torch.float64)
    else:
        w = torch.tensor(_reals("frequencies", frequencies, nonnegative=True),
                         dtype=torch.float64)
    if amplitude is not None and rms is not None:
        raise ValueError(f"give amplitude or rms, not both; got {amplitude} and {rms}")
    a = 1.0 if amplitude is None else _finite("amplitude", amplitude)
    if a < 0:
        raise ValueError(f"amplitude must be >= 0, got {a}")
    if rms is not None and _finite("rms", rms) <= 0:
        raise ValueError(f"rms must be > 0, got {rms}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"seed must be an int, got {type(seed).__name__}: {seed!r}")
    check_choice(phases, "phases", _PHASES)
    k = torch.arange(1, w.numel() + 1, dtype=torch.float64)
    if phases == "random":
        gen = torch.Generator().manual_seed(seed)
        phi = 2 * math.pi * torch.rand(w.numel(), generator=gen, dtype=torch.float64)
    else:  # "schroeder"
        phi = -math.pi * k * (k - 1) / w.numel()
    x = torch.sin(t64[:, None] * w.to(t64.device) + phi.to(t64.device)).sum(-1)
    if rms is not None:
        current = x.square().mean().sqrt()
        if current == 0:
            raise ValueError("the multisine is identically zero on t; cannot scale it to rms")
        x = x * (rms / current)
    else:
        x = a * x
    return x.to(t.dtype)


def chirp(
    t: Tensor,
    *,
    omega0: float,
    omega1: float,
    t1: float | None = None,
    sweep: str = "linear",
    amplitude: float = 1.0,
    phase: float = 0.0,
) -> Tensor:
    """Frequency sweep ``x(t) = a sin(theta(t) + phase)`` with ``theta' = w(t)``, ``theta(0) = 0``.

    ``sweep="linear"``: ``w(t) = w0 + (w1 - w0) t / t1``.
    ``sweep="logarithmic"``: ``w(t) = w0 (w1 / w0) ** (t / t1)`` (``w0, w1 > 0``).
    Time is measured from ``t = 0`` (as in ``scipy.signal.chirp``), not from ``t[0]``.

    Args:
        t: Time in s, ``(time,)``.
        omega0: Angular frequency at ``t = 0`` in rad/s, ``>= 0``.
        omega1: Angular frequency at ``t = t1`` in rad/s, ``>= 0``.
        t1: Time at which ``omega1`` is reached, ``> 0`` (default ``t[-1]``).
        sweep: ``"linear"`` or ``"logarithmic"``.
        amplitude: ``a >= 0``.
        phase: Phase offset in rad.

    Returns:
        x: ``(time,)``, dtype and device of ``t``.

    Raises:
        ValueError: Unknown ``sweep``, negative frequencies (zero for logarithmic),
            ``t1 <= 0``, negative ``amplitude``, bad ``t``.
    """
    t64 = _check_t(t)
    w0, w1 = _finite("omega0", omega0), _finite("omega1", omega1)
    a, phase = _finite("amplitude", amplitude), _finite("phase", phase)
    t1 = float(t64[-1]) if t1 is None else _finite("t1", t1)
    if t1 <= 0:
        raise ValueError(f"t1 must be > 0, got {t1}")
    if a < 0:
        raise ValueError(f"amplitude must be >= 0, got {a}")
    check_choice(sweep, "sweep", _SWEEPS)
    if sweep == "linear":
        if w0 < 0 or w1 < 0:
            raise ValueError(f"omega0 and omega1 must be >= 0, got {w0} and {w1}")
        theta = w0 * t64 + 0.5 * (w1 - w0) / t1 * t64.square()
    else:  # "logarithmic"
        if w0 <= 0 or w1 <= 0:
            raise ValueError(f"omega0 and omega1 must be > 0 for a logarithmic sweep, "
                             f"got {w0} and {w1}")
        if w0 == w1:
            theta = w0 * t64
        else:
            rate = math.log(w1 / w0) / t1
            theta = w0 * torch.expm1(rate * t64) / rate
    return (a * torch.sin(theta + phase)).to(t.dtype)


def exponential_decay(x: Tensor, t: Tensor, *, time_constant: float) -> Tensor:
    """Multiply ``x`` by the envelope ``exp(-(t - t[0]) / time_constant)``.

    Applied to a zero-mean oscillation (sine, multisine) it yields shrinking cycles whose
    turning points open nested minor loops.

    Args:
        x: Signal ``(..., time)``.
        t: Time in s, ``(time,)``.
        time_constant: Decay time constant in s, ``> 0``.

    Returns:
        ``(..., time)``, dtype of ``x``.

    Raises:
        ValueError: ``time_constant <= 0``, mismatched lengths, bad ``t``.
    """
    t64 = _check_t(t)
    tau = _finite("time_constant", time_constant)
    if tau <= 0:
        raise ValueError(f"time_constant must be > 0, got {tau}")
    if not isinstance(x, Tensor) or x.dim() < 1 or x.shape[-1] != t64.shape[0]:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"x must have shape (..., {t64.shape[0]}) matching t, got {shape}")
    env = torch.exp(-(t64 - t64[0]) / tau).to(device=x.device, dtype=x.dtype)
    return x * env


def decaying_sine(
    t: Tensor,
    *,
    amplitude: float = 1.0,
    omega: float = 1.0,
    time_constant: float | None = None,
    phase: float = 0.0,
) -> Tensor:
    """``x(t) = a exp(-(t - t[0]) / tau) sin(omega t + phase)``: nested, shrinking cycles.

    Successive maxima decrease and successive minima increase (each by the factor
    ``exp(-pi / (omega tau))``), so every half-cycle is a minor loop inside the previous one.

    Args:
        t: Time in s, ``(time,)``.
        amplitude: ``a >= 0``.
        omega: Angular frequency in rad/s, ``> 0``.
        time_constant: ``tau > 0`` in s (default: a third of the duration ``t[-1] - t[0]``).
        phase: Phase in rad.

    Returns:
        x: ``(time,)``, dtype and device of ``t``.

    Raises:
        ValueError: Invalid values or ``t``.
    """
    t64 = _check_t(t)
    if _finite("omega", omega) <= 0:
        raise ValueError(f"omega must be > 0, got {omega}")
    duration = float(t64[-1] - t64[0])
    if time_constant is None:
        if duration <= 0:
            raise ValueError("t spans no time; give time_constant explicitly")
        time_constant = duration / 3
    x = sum_of_sines(t64, amplitudes=(amplitude,), frequencies=(omega,), phases=(phase,))
    return exponential_decay(x, t64, time_constant=time_constant).to(t.dtype)


def nested_reversals(
    t: Tensor,
    *,
    amplitude: float = 1.0,
    n_reversals: int = 10,
    ratio: float = 0.8,
    center: float = 0.0,
) -> Tensor:
    """Signal with extrema ``x_max, x_min, smaller max, larger min, ...`` (return-point tests).

    Starting at ``center``, the signal moves through the extrema
    ``e_k = center + (-1)^k amplitude ratio^k`` for ``k = 0 .. n_reversals - 1``, reaching
    ``e_k`` at ``t[0] + (k + 1) D / n_reversals`` with ``D = t[-1] - t[0]``. Between extrema
    it follows a half-cosine, so it is smooth, strictly monotone between turning points
    and its turning points are exactly the ``e_k``.

    Args:
        t: Time in s, ``(time,)`` with ``t[-1] > t[0]``.
        amplitude: First excursion ``> 0``.
        n_reversals: Number of extrema ``>= 1``.
        ratio: Shrink factor of successive excursions, ``0 < ratio < 1``.
        center: Level around which the extrema nest.

    Returns:
        x: ``(time,)``, dtype and device of ``t``.

    Raises:
        ValueError: Invalid values or ``t``.
    """
    t64 = _check_t(t)
    a, r, c = _finite("amplitude", amplitude), _finite("ratio", ratio), _finite("center", center)
    if a <= 0:
        raise ValueError(f"amplitude must be > 0, got {a}")
    if not 0 < r < 1:
        raise ValueError(f"ratio must satisfy 0 < ratio < 1, got {r}")
    check_int(n_reversals, "n_reversals", minimum=1)
    duration = float(t64[-1] - t64[0])
    if duration <= 0:
        raise ValueError("t must span a positive duration for nested_reversals")
    k = torch.arange(n_reversals, dtype=torch.float64, device=t64.device)
    levels = torch.cat([k.new_zeros(1), (-1.0) ** k * a * r**k]) + c
    s = ((t64 - t64[0]) / duration * n_reversals).clamp(0, n_reversals)
    seg = s.floor().clamp(max=n_reversals - 1).long()
    frac = s - seg
    blend = 0.5 * (1 - torch.cos(math.pi * frac))
    x = levels[seg] + (levels[seg + 1] - levels[seg]) * blend
    return x.to(t.dtype)


def to_range(x: Tensor, low: float | Tensor, high: float | Tensor) -> Tensor:
    """Affinely rescale ``x`` along its last axis so that its minimum is ``low``, maximum ``high``.

    Useful to give a test signal exactly the range of a training signal:
    ``to_range(multisine(t, band=(0.2, 3.0), seed=1), x.min(), x.max())``.

    Args:
        x: Signal ``(..., time)``; every sequence must be non-constant.
        low: Target minimum (float or 0-dim tensor).
        high: Target maximum, ``> low``.

    Returns:
        ``(..., time)``, dtype of ``x``; differentiable in ``x``.

    Raises:
        ValueError: ``low >= high``, non-finite values, a constant sequence, empty ``x``.
        TypeError: ``x`` not a floating tensor.
    """
    if not isinstance(x, Tensor) or not x.is_floating_point():
        raise TypeError(f"x must be a floating torch.Tensor, got {getattr(x, 'dtype', type(x))}")
    if x.dim() < 1 or x.shape[-1] < 2:
        raise ValueError(f"x must have shape (..., time) with time >= 2, got {tuple(x.shape)}")
    lo, hi = float(low), float(high)
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo >= hi:
        raise ValueError(f"need finite low < high, got low={lo}, high={hi}")
    if not torch.isfinite(x).all():
        raise ValueError("x must be finite, got NaN or inf values")
    x_min = x.amin(-1, keepdim=True)
    x_max = x.amax(-1, keepdim=True)
    if (x_max == x_min).any():
        raise ValueError("x contains a constant sequence, which cannot be rescaled to a range")
    return lo + (x - x_min) * ((hi - lo) / (x_max - x_min))
