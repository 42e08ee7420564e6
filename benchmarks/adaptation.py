"""Closed-loop tracking on drifting plants: the harness of the adaptive compensator, and its
two baselines (the static compensator, the static compensator plus a PI feedback loop).

    python benchmarks/adaptation.py [--quick] [--plants paper stage bouc_wen] [--out DIR]

Each plant is identified once, undrifted, then run sample by sample in a loop with a
controller on a reference it never saw while its gain and loop width drift. Scored: the
tracking RMSE ``y_t - r_t`` in % of the reference's range over the whole run and over its
second half.

Plants (simulated here one sample at a time, float64; undrifted they equal the batch plants
of ``benchmarks/compensation.py``: ``tests/test_benchmark_scripts.py`` checks it):
    * paper: the paper's plant, ``y = g(s) sum_i play(u; w(s) d_i)``, the 15 unit plays of
      :func:`~torchhys.plants.paper_plant_widths` (full widths ``d_i``).
    * stage: :class:`~torchhys.plants.PiezoStage` (8 Hz, zeta 0.07, 160 Hz, zero-order hold)
      with its hysteresis ``h = g(s) (0.5 u + 0.1 sum_i play(u; w(s) d_i))``
      (:func:`~torchhys.plants.default_stage_hysteresis`, widths ``k / 3``); ``y_t`` depends
      on ``h`` up to ``t - 1`` (one sample of delay).
    * bouc_wen: ``y = g(s) (k_x u + k_w w)``, ``dw = A(s) du - beta |du| |w|^(n-1) w - gamma du
      |w|^n`` with ``A(s) = w(s) A`` (the loop's height and width grow with ``A``), the
      defaults of :data:`torchhys.plants.bouc_wen.DEFAULTS`, one RK4 step in ``u`` per sample.

Drifts (``s = t / (T - 1)`` the run's progress, ``d(s)`` in [0, 1]; gain ``g = 1 + 0.3 d``,
width ``w = 1 + 0.4 d``): none ``d = 0``; ramp ``d = s``; step ``d = [s >= 1/2]``; thermal
cycle ``d = (1 - cos(4 pi s)) / 2`` (two warm-ups and cool-downs over the run).

The static compensator: the identified Prandtl-Ishlinskii inverse of
``benchmarks/compensation.py`` (:func:`identify_pi`: NNLS over 20 plays on the plant's
excitation record, :func:`training_input`), deployed with
:class:`~torchhys.deploy.streaming.StreamingCompensator` (commands saturated to the record's
input range widened by 5 %), stepped once per sample on the reference. Static + PI: the same
feedforward plus ``kp e + ki sum e`` on the last measured error ``e = r_{t-1} - y_{t-1}``,
the sum saturated to the same limits (conditional integration: it does not grow while the
command is saturated); ``kp = a / k``, ``ki = b / k`` (``k`` the record's static gain) with
``(a, b)`` the pair of :data:`PI_GRID` with which the PI alone (no feedforward) tracks the
undrifted plant's output on the excitation record's first third (the multisine) with the
smallest RMSE, among the pairs that keep a gain margin of 2 (with the plant's gain doubled
the PI alone tracks no worse): the loop tuned on the plant, not on the compensator's
residual (which, with an exact compensator, would pick the weakest PI), and on no scored
reference.

A row is a function ``make(fit) -> step`` with ``step(reference_t, measured_prev,
applied_prev) -> command`` (:class:`Step`): the adaptive compensator is one more entry of
:data:`ROWS`, fed the measured response and the applied (saturated) command.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a file: the checkout
from benchmarks.compensation import (  # noqa: E402
    STAGE,
    STAGE_FS,
    fade_in,
    identify_pi,
    static_line,
    training_input,
)
from torchhys.deploy.adaptive import AdaptiveCompensator  # noqa: E402
from torchhys.deploy.streaming import StreamingCompensator  # noqa: E402
from torchhys.plants import default_stage_hysteresis, paper_plant_widths  # noqa: E402
from torchhys.plants.bouc_wen import DEFAULTS as BW  # noqa: E402
from torchhys.signals import multisine, to_range  # noqa: E402

GAIN_DRIFT, WIDTH_DRIFT = 0.3, 0.4
DRIFTS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "none": lambda s: np.zeros_like(s),
    "ramp": lambda s: s,
    "step": lambda s: (s >= 0.5).astype(float),
    "thermal cycle": lambda s: 0.5 * (1.0 - np.cos(4.0 * np.pi * s)),
}
#: the PI's gains keep the loop tracking no worse with the plant's gain times this
GAIN_MARGIN = 2.0
#: normalised PI gains (a, b) searched: kp = a / k, ki = b / k
PI_GRID = [(a, b) for a in (0.0, 0.1, 0.3)
           for b in (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)]


def play(state: np.ndarray, u: float, widths: np.ndarray) -> np.ndarray:
    """One step of plays of full widths ``widths`` (torchhys's backlash)."""
    return np.minimum(u + widths / 2, np.maximum(u - widths / 2, state))


class DriftingPlant:
    """A plant stepped one sample at a time with a gain and a loop-width factor per step."""

    def reset(self) -> None:
        raise NotImplementedError

    def step(self, u: float, gain: float, width: float) -> float:
        raise NotImplementedError


class PaperPlant(DriftingPlant):
    def __init__(self) -> None:
        self.d = paper_plant_widths(torch.float64).numpy()
        self.reset()

    def reset(self) -> None:
        self.p = np.zeros_like(self.d)

    def step(self, u: float, gain: float, width: float) -> float:
        self.p = play(self.p, u, width * self.d)
        return gain * float(self.p.sum())


class StagePlant(DriftingPlant):
    def __init__(self, fs: float = STAGE_FS) -> None:
        hys = default_stage_hysteresis()
        self.d = hys.fixed_widths.double().numpy()
        self.wts = hys.weights.double().numpy()
        self.lin = float(hys.linear_weight)
        A, B, _, _ = STAGE.matrices(1.0 / fs)
        self.A, self.B = A.numpy(), B.numpy()
        self.reset()

    def reset(self) -> None:
        self.p, self.s = np.zeros_like(self.d), np.zeros(2)

    def step(self, u: float, gain: float, width: float) -> float:
        self.p = play(self.p, u, width * self.d)
        h = gain * (self.lin * u + float(self.wts @ self.p))
        y = float(self.s[0])
        self.s = self.A @ self.s + self.B * h
        return y


class BoucWenPlant(DriftingPlant):
    def reset(self) -> None:
        self.w, self.u = 0.0, None

    def __init__(self) -> None:
        self.reset()

    def step(self, u: float, gain: float, width: float) -> float:
        if self.u is not None:
            h, a, n = u - self.u, BW["A"] * width, BW["n"]
            b = BW["beta"] * math.copysign(1.0, h) if h != 0 else 0.0

            def g(w: float) -> float:
                return a - (b * math.copysign(1.0, w) + BW["gamma"]) * max(abs(w), 1e-300) ** n

            k1 = g(self.w)
            k2 = g(self.w + 0.5 * h * k1)
            k3 = g(self.w + 0.5 * h * k2)
            k4 = g(self.w + h * k3)
            self.w += h / 6 * (k1 + 2 * (k2 + k3) + k4)
        self.u = u
        return gain * (BW["k_x"] * u + BW["k_w"] * self.w)


#: name -> (plant, samples per 60 s of the fit record and the reference, full / quick)
PLANTS: dict[str, tuple[Callable[[], DriftingPlant], int, int]] = {
    "paper": (PaperPlant, 2000, 400),
    "stage": (StagePlant, int(60 * STAGE_FS) + 1, int(60 * STAGE_FS) + 1),
    "bouc_wen": (BoucWenPlant, 2000, 400),
}


class Step(Protocol):
    """One controller sample: the command for ``reference_t`` given the output measured at
    ``t - 1`` and the command applied (after saturation) at ``t - 1``."""

    def __call__(self, reference_t: float, measured_prev: float, applied_prev: float
                 ) -> float: ...


class Fit:
    """What is identified on the undrifted plant, once: its excitation record ``(u, y)``, the
    record's static gain, the command limits, the inverse model and the PI gains ``(a, b)``."""

    def __init__(self, plant: str, u: torch.Tensor, y: torch.Tensor, gain: float,
                 limits: tuple[float, float], model: torch.nn.Module,
                 pi_gains: tuple[float, float] = (0.0, 0.0)) -> None:
        self.plant, self.u, self.y, self.gain = plant, u, y, gain
        self.limits, self.model, self.pi_gains = limits, model, pi_gains


def simulate(plant: DriftingPlant, u: np.ndarray, drift: np.ndarray | None = None) -> np.ndarray:
    """Open loop: the plant's output for the command ``u`` (with drift profile ``d``)."""
    d = np.zeros(len(u)) if drift is None else drift
    plant.reset()
    return np.array([plant.step(float(v), 1 + GAIN_DRIFT * e, 1 + WIDTH_DRIFT * e)
                     for v, e in zip(u, d, strict=True)])


def closed_loop(plant: DriftingPlant, step: Step, ref: np.ndarray, drift: np.ndarray,
                gain: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Run ``step`` in a loop with ``plant`` (its gain times ``gain``): (outputs y_t, commands
    u_t)."""
    plant.reset()
    y, u = np.zeros(len(ref)), np.zeros(len(ref))
    y_prev = u_prev = 0.0  # the plant at rest
    for t, (r, e) in enumerate(zip(ref, drift, strict=True)):
        u[t] = step(float(r), y_prev, u_prev)
        y[t] = y_prev = plant.step(u[t], gain * (1 + GAIN_DRIFT * e), 1 + WIDTH_DRIFT * e)
        u_prev = u[t]
    return y, u


def static_step(fit: Fit) -> Step:
    """The static compensator: the deployed inverse, stepped on the reference alone."""
    comp = StreamingCompensator(fit.model, limits=fit.limits)

    def step(reference_t: float, measured_prev: float, applied_prev: float) -> float:
        return float(comp.step(torch.tensor([reference_t], dtype=torch.float64))[0])

    return step


def pi_step(fit: Fit, gains: tuple[float, float] | None = None, *, feedforward: bool = True
            ) -> Step:
    """The static compensator plus a discrete PI on the last measured tracking error
    (``feedforward=False``: the PI alone, as it is tuned)."""
    a, b = fit.pi_gains if gains is None else gains
    kp, ki = a / fit.gain, b / fit.gain
    low, high = fit.limits
    ff = static_step(fit) if feedforward else (lambda r, y, u: 0.0)
    mem = {"r": None, "i": 0.0}

    def step(reference_t: float, measured_prev: float, applied_prev: float) -> float:
        e = 0.0 if mem["r"] is None else mem["r"] - measured_prev
        mem["r"] = reference_t
        u_ff = ff(reference_t, measured_prev, applied_prev)
        integral = mem["i"] + ki * e
        u = u_ff + kp * e + integral
        if low <= u <= high:  # conditional integration: hold the sum while saturated
            mem["i"] = integral
        return min(max(u_ff + kp * e + mem["i"], low), high)

    return step


#: the adaptive rows' options, chosen by ``benchmarks/adaptation_tuning.py`` on validation
#: references (their own seed) of every plant, never on the scored one (docs/adaptation.md)
ADAPTIVE: dict[str, dict[str, float]] = {
    "rls": {"forgetting": 0.995, "adapt_bound": 1.0, "dead_zone": 0.0, "excitation": 1e-2},
    "nlms": {"nlms_step": 0.2, "adapt_bound": 0.5, "dead_zone": 0.0, "excitation": 1e-3},
}


def adaptive_compensator(fit: Fit, adapt: str, **options: float) -> torch.jit.ScriptModule:
    """The static row's inverse with its readout adapted online (TorchScript: half the
    eager step's time). A Prandtl-Ishlinskii inverse records no input range or direction:
    the record's output range and "increasing" are given."""
    kwargs = {**ADAPTIVE[adapt], **options}
    comp = AdaptiveCompensator(fit.model, adapt=adapt, limits=fit.limits,
                               input_range=(float(fit.y.min()), float(fit.y.max())),
                               direction="increasing", **kwargs)
    return torch.jit.script(comp)


def adaptive_step(fit: Fit, adapt: str = "rls", **options: float) -> Step:
    """The adaptive compensator fed the measured response and the applied command."""
    comp = adaptive_compensator(fit, adapt, **options)
    buf = torch.zeros(3, 1, dtype=torch.float64)

    def step(reference_t: float, measured_prev: float, applied_prev: float) -> float:
        buf[0, 0], buf[1, 0], buf[2, 0] = reference_t, measured_prev, applied_prev
        return float(comp.step(buf[0], measured_prev=buf[1], applied_prev=buf[2])[0])

    step.compensator = comp  # type: ignore[attr-defined]
    return step


ROWS: dict[str, Callable[[Fit], Step]] = {
    "static compensator": static_step,
    "static + PI": pi_step,
    "adaptive RLS": lambda fit: adaptive_step(fit, "rls"),
    "adaptive NLMS": lambda fit: adaptive_step(fit, "nlms"),
}


def reference(fit: Fit, n: int, seed: int = 11) -> np.ndarray:
    """An unseen multisine over 3 x 60 s (3n samples), 90 % of the record's output range,
    starting at rest (the middle of the range)."""
    t = torch.linspace(0.0, 180.0, 3 * n - 2, dtype=torch.float64)
    low, high = float(fit.y.min()), float(fit.y.max())
    mid, half = 0.5 * (low + high), 0.45 * (high - low)
    sig = to_range(multisine(t, band=(0.1, 1.5), n_tones=12, seed=seed), mid - half, mid + half)
    return fade_in(sig, t, mid).numpy()


def rmse_pct(y: np.ndarray, ref: np.ndarray) -> float:
    return 100.0 * float(np.sqrt(np.mean((y - ref) ** 2))) / float(ref.max() - ref.min())


def identify(name: str, n: int) -> Fit:
    """The static compensator from the undrifted plant's excitation record, and the PI gains
    tuned on it."""
    make, *_ = PLANTS[name]
    u = training_input(6.0, n).double()
    y = torch.from_numpy(simulate(make(), u.numpy()))
    k, _ = static_line(u, y)
    limits = (float(u.min()) * 1.05, float(u.max()) * 1.05)
    fit = Fit(name, u, y, k, limits, identify_pi(u, y, k).inverse())
    ref, flat = y[:n].numpy(), np.zeros(n)
    scores = {}
    for g in PI_GRID:
        alone = pi_step(fit, g, feedforward=False)
        score = rmse_pct(closed_loop(make(), alone, ref, flat)[0], ref)
        doubled = pi_step(fit, g, feedforward=False)
        if rmse_pct(closed_loop(make(), doubled, ref, flat, GAIN_MARGIN)[0], ref) <= score:
            scores[g] = score  # a gain margin of 2: twice the plant's gain tracks no worse
    if not scores:
        raise RuntimeError(f"{name}: no PI gains of PI_GRID keep a gain margin of {GAIN_MARGIN}")
    fit.pi_gains = min(scores, key=scores.get)
    return fit


def run(names: list[str], quick: bool, log: list[str]) -> tuple[list[tuple], dict]:
    """``(rows, traces)``: a row ``(plant, drift, method, rmse all, rmse 2nd half)`` per run;
    the traces ``{plant: {method: error over time}}`` of the ramp."""
    rows, traces = [], {}
    for name in names:
        make, n_full, n_quick = PLANTS[name]
        n = n_quick if quick else n_full
        start = time.perf_counter()
        fit = identify(name, n)
        ref = reference(fit, n if not quick or name != "stage" else n // 6)
        s = np.linspace(0.0, 1.0, len(ref))
        log.append(f"{name}: identified and PI tuned in {time.perf_counter() - start:.1f} s, "
                   f"static gain {fit.gain:.3f}, PI (a, b) = {fit.pi_gains}, "
                   f"{len(ref)} samples per run")
        half = len(ref) // 2
        for drift, profile in DRIFTS.items():
            for method, make_row in ROWS.items():
                y, _ = closed_loop(make(), make_row(fit), ref, profile(s))
                rows.append((name, drift, method, rmse_pct(y, ref),
                             rmse_pct(y[half:], ref[half:])))
                if drift == "ramp":
                    traces.setdefault(name, {})[method] = (y - ref) / np.ptp(ref) * 100
    return rows, traces


def plot(traces: dict, path: Path) -> None:
    """The ramp's tracking error over time, a panel per plant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(traces), 1, figsize=(9, 2.6 * len(traces)), squeeze=False)
    for ax, (name, rows) in zip(axes[:, 0], traces.items(), strict=True):
        for method, err in rows.items():
            ax.plot(np.linspace(0, 1, len(err)), err, lw=0.7, label=method)
        ax.set(title=f"{name}: gain +{GAIN_DRIFT:.0%} and width factor +{WIDTH_DRIFT:.0%}, "
                     "ramped over the run", xlabel="run progress s", ylabel="error (% range)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short runs (smoke test)")
    parser.add_argument("--plants", nargs="+", choices=list(PLANTS), default=list(PLANTS))
    parser.add_argument("--out", type=Path, default=None,
                        help="folder for the figure adaptation_ramp.png (default: none)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    log: list[str] = []
    start = time.perf_counter()
    rows, traces = run(args.plants, args.quick, log)
    print("\n".join(log))
    print(f"\ntotal {time.perf_counter() - start:.0f} s\n")
    print("| plant | drift | method | RMSE (%) | RMSE 2nd half (%) | 2nd half / static |")
    print("|---|---|---|---|---|---|")
    static = {(r[0], r[1]): r[4] for r in rows if r[2] == "static compensator"}
    for name, drift, method, whole, second in rows:
        print(f"| {name} | {drift} | {method} | {whole:.3f} | {second:.3f} | "
              f"{second / static[name, drift]:.3f} |")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        plot(traces, args.out / "adaptation_ramp.png")


if __name__ == "__main__":
    main()
