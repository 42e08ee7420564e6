"""The adaptive step in C (torchhys.deploy.c.to_c with adapt="rls" / "nlms"): the compiled
C (float64) against the eager AdaptiveCompensator over a closed loop with a drifting plant,
noise, NaN bursts and 10x outliers in the measured response (the pairs the eager run saw are
replayed into the C step); PREFIX_weights against adapted_weights(), the counters,
PREFIX_init back to the offline weights, a float32 build, -ffast-math refused, and the new
templates (all, any, diagonal, square) against torch. Skipped without a C compiler."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from _export_helpers import CC, FLAGS, FLOAT32_RTOL, NO_CC
from test_adaptive_compensator import conditioned_net

import torchhys
from torchhys import InverseHysteresisNet, PrandtlIshlinskii
from torchhys.deploy.adaptive import AdaptiveCompensator
from torchhys.deploy.c import to_c

pytestmark = pytest.mark.skipif(CC is None, reason=NO_CC)
D = torch.float64
OPTS = {"limits": (-10.0, 10.0), "direction": "increasing", "input_range": (-2.5, 2.5)}
PLANT_R = np.array([0.0, 0.4, 0.9, 1.5])
PLANT_W = np.array([0.6, 0.3, 0.2, 0.1])


def pi_inverse() -> torchhys.PrandtlIshlinskiiInverse:
    """The inverse of the plant's Prandtl-Ishlinskii model (its 4 plays, linear weight 0.3)."""
    pi = PrandtlIshlinskii(torch.tensor(PLANT_R, dtype=D), torch.tensor(PLANT_W, dtype=D),
                           linear_weight=0.3)
    return pi.inverse()


def signal(n: int, seed: int = 0, amp: float = 2.0) -> np.ndarray:
    """Three tones under a slow amplitude modulation, within about +-amp."""
    g = np.random.default_rng(seed)
    ph = g.uniform(0, 6.28, 3)
    t = np.arange(n) / 200.0
    s = (np.sin(2.1 * t + ph[0]) + 0.5 * np.sin(5.3 * t + ph[1])
         + 0.3 * np.sin(11.7 * t + ph[2]))
    return amp / 1.8 * s * (0.6 + 0.4 * np.cos(0.37 * t))


def identity_net() -> InverseHysteresisNet:
    """Three plays and an identity readout, fitted by least squares to the PI inverse."""
    from torchhys.selection.candidates import solve_readout
    from torchhys.selection.folds import Batch

    net = InverseHysteresisNet([torchhys.Backlash(torch.tensor([0.3, 0.8, 1.4]))], hidden=1,
                               activation="identity").double()
    y = torch.tensor(signal(3000, seed=5), dtype=D)
    u, _ = pi_inverse()(y)
    net.fit_normalization(y, u)
    solve_readout(net, Batch(y[None], u[None], torch.ones(1, y.numel(), dtype=torch.bool)))
    return net


MODELS = {"pi_inverse": pi_inverse, "identity_net": identity_net}


def closed_loop(comp: AdaptiveCompensator, n: int, seed: int = 1) -> dict:
    """The eager compensator against a plant (the PI model, its gain drifting by +25 % and
    an offset), the measured response noisy, with NaN bursts and 10x outliers: the rows
    (desired, measured_prev, applied_prev) it saw, its commands, weights and counters."""
    g = np.random.default_rng(seed)
    x = signal(n, seed)
    plays, y_prev, u_prev = np.zeros(len(PLANT_R)), np.nan, np.nan
    rows, us = [], []
    dt = comp.low.dtype
    for t in range(n):
        rows.append((x[t], y_prev, u_prev))
        u = float(comp.step(torch.tensor([x[t]], dtype=dt),
                            measured_prev=torch.tensor([y_prev], dtype=dt),
                            applied_prev=torch.tensor([u_prev], dtype=dt)))
        us.append(u)
        plays = np.maximum(u - PLANT_R, np.minimum(u + PLANT_R, plays))
        gain = 1.0 + 0.25 * t / n
        y = gain * (PLANT_W @ plays + 0.3 * u) + 0.02 * t / n + 0.002 * g.standard_normal()
        if t % 997 in range(5, 12):  # a burst of NaN
            y = np.nan
        elif t % 613 == 7:  # an outlier
            y *= 10.0
        elif t % 1499 == 3:
            y = np.inf
        y_prev, u_prev = y, u
    return {"rows": rows, "u": np.array(us), "weights": comp.adapted_weights()[0].double(),
            "counts": [int(comp.updates_count()), int(comp.skipped_count()),
                       int(comp.refused_count()), int(comp.nonfinite_count()),
                       int(comp.out_of_range_count())]}


DRIVER = r"""
#include <stdio.h>
#include "NAME.h"

int main(void)
{
    static NAME_state s;
    double x, m, a;
    NAME_real w[NAME_N_WEIGHTS];
    int i;
    NAME_init(&s);
    while (scanf("%lf %lf %lf", &x, &m, &a) == 3)
        printf("%.17g\n", (double)NAME_step_adapt(&s, (NAME_real)x, (NAME_real)m,
                                                  (NAME_real)a));
    NAME_weights(&s, w);
    printf("W");
    for (i = 0; i < NAME_N_WEIGHTS; ++i)
        printf(" %.17g", (double)w[i]);
    printf("\nC %lld %lld %lld %lld %lld\n", (long long)NAME_updates_count(&s),
           (long long)NAME_skipped_count(&s), (long long)NAME_refused_count(&s),
           (long long)NAME_nonfinite_count(&s), (long long)NAME_out_of_range_count(&s));
    NAME_init(&s);
    NAME_weights(&s, w);
    printf("R");
    for (i = 0; i < NAME_N_WEIGHTS; ++i)
        printf(" %.17g", (double)w[i]);
    printf("\nC %lld %lld %lld\n", (long long)NAME_updates_count(&s),
           (long long)NAME_skipped_count(&s), (long long)NAME_refused_count(&s));
    return 0;
}
"""


def run_c(folder: Path, rows: list, prefix: str = "ad", flags: list[str] = FLAGS) -> dict:
    """The driver over ``folder/PREFIX.c`` fed ``rows``: commands, weights, counters, the
    weights and counters after PREFIX_init."""
    (folder / "main.c").write_text(DRIVER.replace("NAME", prefix))
    exe = folder / "run"
    subprocess.run([CC, *flags, "-I", str(folder), "-o", str(exe), str(folder / "main.c"),
                    str(folder / f"{prefix}.c"), "-lm"], check=True)
    text = "\n".join(" ".join(repr(float(v)) for v in row) for row in rows)
    lines = subprocess.run([str(exe)], input=text, capture_output=True, text=True,
                           check=True).stdout.split("\n")
    u = np.array([float(v) for v in lines[:len(rows)]])
    rest = [line.split() for line in lines[len(rows):] if line]
    return {"u": u, "weights": torch.tensor([float(v) for v in rest[0][1:]], dtype=D),
            "counts": [int(v) for v in rest[1][1:]],
            "reset_weights": torch.tensor([float(v) for v in rest[2][1:]], dtype=D),
            "reset_counts": [int(v) for v in rest[3][1:]]}


def gap(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    assert np.isfinite(a).all() and np.isfinite(b).all()
    return float(np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b))))


def check_parity(tmp_path: Path, name: str, method: str, n: int, **options) -> list:
    model = MODELS[name]()
    opts = {**OPTS, **options}
    ref = closed_loop(AdaptiveCompensator(model, adapt=method, **opts), n)
    to_c(model, tmp_path, prefix="ad", adapt=method, **opts)
    got = run_c(tmp_path, ref["rows"])
    assert gap(got["u"], ref["u"]) <= 1e-12, gap(got["u"], ref["u"])
    assert gap(got["weights"], ref["weights"]) <= 1e-12
    assert got["counts"] == ref["counts"]
    updates, skipped, _, _, _ = ref["counts"]
    assert updates > n // 10 and skipped > 5  # the loop adapted and skipped
    fresh = AdaptiveCompensator(model, adapt=method, **opts)
    assert not torch.equal(ref["weights"], fresh.offline_weights().double())
    assert torch.equal(got["reset_weights"], fresh.offline_weights().double())
    assert got["reset_counts"] == [0, 0, 0]
    return got["counts"]


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("method", ["rls", "nlms"])
def test_c_equals_the_eager_adaptive_compensator(tmp_path: Path, name: str,
                                                 method: str) -> None:
    check_parity(tmp_path, name, method, 2000)


@pytest.mark.parametrize("method", ["rls", "nlms"])
def test_c_without_a_direction_equals_the_eager_one(tmp_path: Path, method: str) -> None:
    """No guard: no update is refused (the count stays 0 in both)."""
    assert check_parity(tmp_path, "pi_inverse", method, 2000, direction="none")[2] == 0


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("method", ["rls", "nlms"])
def test_c_equals_the_eager_adaptive_compensator_long(tmp_path: Path, name: str,
                                                      method: str) -> None:
    check_parity(tmp_path, name, method, 10_000)


@pytest.mark.parametrize("method", ["rls", "nlms"])
def test_a_float32_build_stays_within_float32_tolerance(tmp_path: Path, method: str) -> None:
    """The float32 C against the float32 eager compensator (the same pairs): within the
    float32 bound of docs/deployment.md (1e-4 of the scale), the counters equal."""
    model = pi_inverse().float()
    ref = closed_loop(AdaptiveCompensator(model, adapt=method, **OPTS), 1500)
    to_c(model, tmp_path, prefix="ad", adapt=method, dtype=torch.float32, **OPTS)
    header = (tmp_path / "ad.h").read_text()
    assert "typedef float ad_real;" in header
    got = run_c(tmp_path, ref["rows"])
    assert gap(got["u"], ref["u"]) <= FLOAT32_RTOL, gap(got["u"], ref["u"])
    assert gap(got["weights"], ref["weights"]) <= FLOAT32_RTOL
    assert got["counts"] == ref["counts"]


def test_fast_math_is_refused_and_the_header_states_the_contract(tmp_path: Path) -> None:
    to_c(pi_inverse(), tmp_path, prefix="ad", adapt="nlms", **OPTS)
    done = subprocess.run([CC, "-std=c99", "-O2", "-ffast-math", "-c", str(tmp_path / "ad.c"),
                           "-o", str(tmp_path / "ad.o")], capture_output=True, text=True)
    assert done.returncode != 0 and "-ffast-math" in done.stderr
    header = (tmp_path / "ad.h").read_text()
    assert ("ad_real ad_step_adapt(ad_state *s, ad_real desired, ad_real measured_prev, "
            "ad_real applied_prev);") in header
    assert "#define ad_N_WEIGHTS 5" in header and "NDEBUG" in header
    assert "ad_real ad_step(" not in header and "P[" not in header  # NLMS: no covariance
    to_c(pi_inverse(), tmp_path, prefix="ad", adapt="rls", **OPTS)
    assert "ad_real P[25];" in (tmp_path / "ad.h").read_text()


def test_a_null_state_asserts_unless_ndebug(tmp_path: Path) -> None:
    to_c(pi_inverse(), tmp_path, prefix="ad", adapt="nlms", **OPTS)
    (tmp_path / "null.c").write_text('#include "ad.h"\nint main(void)\n{\n'
                                     "    return (int)ad_updates_count((const ad_state *)0);\n}\n")
    exe = tmp_path / "null"
    subprocess.run([CC, *FLAGS, "-I", str(tmp_path), "-o", str(exe), str(tmp_path / "null.c"),
                    str(tmp_path / "ad.c"), "-lm"], check=True)
    done = subprocess.run([str(exe)], capture_output=True, text=True)
    assert done.returncode != 0 and "s != NULL" in done.stderr


def test_a_static_export_has_no_adaptive_parts(tmp_path: Path) -> None:
    to_c(pi_inverse(), tmp_path, prefix="st", **OPTS)
    header = (tmp_path / "st.h").read_text()
    assert "st_step_adapt" not in header and "N_WEIGHTS" not in header
    assert "assert" not in (tmp_path / "st.c").read_text()


# --- the templates the adaptive graph added -------------------------------------------------


class _Ops(torch.nn.Module):
    def forward(self, x: torch.Tensor, a: torch.Tensor, b: torch.Tensor
                ) -> tuple[torch.Tensor, ...]:
        m = a.view(1, 3, 3)
        return (torch.diagonal(m, 0, 1, 2) * 2.0, torch.diagonal(m, 1, 1, 2) + 0.0,
                torch.diagonal(m, -1, 1, 2) + 0.0, a.square(),
                (a > b).all(1).to(a.dtype), (a > b).any(1).to(a.dtype),
                a.all(1).to(a.dtype), a.any(1).to(a.dtype),
                (m > 0).all(2).to(a.dtype) - (m < 0).any(2).to(a.dtype))


def _c_array(values: list[float]) -> str:
    return "{" + ", ".join("NAN" if np.isnan(v) else repr(v) for v in values) + "}"


def test_the_new_templates_equal_torch(tmp_path: Path) -> None:
    """diagonal (offsets 0, 1, -1), square, all and any (of bools and of floats: a NaN and
    -0.0 among them) written as C and run: equal to torch bit for bit."""
    from torchhys.deploy.c._graph import translate
    from torchhys.deploy.c._writer import Writer

    a = torch.tensor([[0.5, -1.0, 0.0, 2.0, np.nan, -0.0, 3.0, 1.0, -2.0]], dtype=D)
    b = torch.tensor([[0.0, -2.0, -1.0, 1.0, 0.0, -1.0, 2.0, 0.0, -3.0]], dtype=D)
    x = torch.zeros(1, dtype=D)
    ep = torch.export.export(_Ops(), (x, a, b), strict=False)
    w = Writer("ops")
    u, outs = translate(ep, w, ["B"], inputs=["A"])
    outs = [w.materialize(t) for t in (u, *outs)]
    w.node += 1
    for t in outs:
        for i in range(t.numel):
            idx = [str(int(j)) for j in np.unravel_index(i, t.shape)]
            w.emit(f'printf("%.17g\\n", (double)({w.read(t, idx)}));')
    decls, body = w.shared_locals()
    src = ["#include <math.h>", "#include <stdint.h>", "#include <stdio.h>",
           "#include <string.h>", *w.helpers.values(), *w.constants, "int main(void)", "{",
           f"    const double A[9] = {_c_array(a[0].tolist())};",
           f"    const struct {{ double B[9]; }} s_ = {{{_c_array(b[0].tolist())}}}, *s = &s_;",
           *[f"    {d}" for d in decls], *body, "    return 0;", "}"]
    (tmp_path / "ops.c").write_text("\n".join(src) + "\n")
    exe = tmp_path / "ops"
    subprocess.run([CC, "-std=c99", "-O2", "-o", str(exe), str(tmp_path / "ops.c"), "-lm"],
                   check=True)
    got = [float(v) for v in subprocess.run([str(exe)], capture_output=True, text=True,
                                            check=True).stdout.split()]
    ref = torch.cat([t.reshape(-1) for t in _Ops()(x, a, b)]).tolist()
    assert len(got) == len(ref)
    for g_, r in zip(got, ref, strict=True):
        assert (np.isnan(g_) and np.isnan(r)) or (g_ == r and np.signbit(g_) == np.signbit(r)), (
            got, ref)


def test_the_controller_in_adaptive_mode_equals_the_eager_compensator(tmp_path: Path) -> None:
    """deploy/c/controller.c built with CFLAGS=-DCOMP_ADAPT (deploy/c/build.sh): REF.csv's
    second column the measured response, the commands within 1e-12 of the eager closed
    loop's, the counters and the logged weights (--log-every) equal."""
    import os

    root = Path(__file__).resolve().parents[1]
    model = identity_net()
    comp = AdaptiveCompensator(model, adapt="nlms", **OPTS)
    n = 1200
    ref = closed_loop(comp, n)
    to_c(model, tmp_path, prefix="ad", adapt="nlms", **OPTS)
    done = subprocess.run(["bash", str(root / "deploy" / "c" / "build.sh"), str(tmp_path),
                           str(tmp_path), "ad"], capture_output=True, text=True,
                          env={**os.environ, "CC": CC, "CFLAGS": "-DCOMP_ADAPT"})
    assert done.returncode == 0, done.stderr
    measured = [r[1] for r in ref["rows"][1:]] + [float("nan")]
    (tmp_path / "ref.csv").write_text("y_ref,y_measured\n" + "".join(
        f"{float(r[0])!r},{float(m)!r}\n" for r, m in zip(ref["rows"], measured, strict=True)))
    run = subprocess.run([str(tmp_path / "controller"), str(tmp_path / "ref.csv"),
                          str(tmp_path / "out.csv"), "--log-every", "500"],
                         capture_output=True, text=True, check=True)
    u = np.loadtxt(tmp_path / "out.csv", delimiter=",", skiprows=1)[:, 1]
    assert gap(u, ref["u"]) <= 1e-12, gap(u, ref["u"])
    lines = run.stdout.splitlines()
    counts = next(line for line in lines if line.startswith("updates ")).split()
    assert [int(v) for v in counts[1::2]] == ref["counts"][:3]
    logged = [line.split() for line in lines if line.startswith("weights ")]
    assert [int(row[1]) for row in logged] == [0, 500, 1000]
    fresh = AdaptiveCompensator(model, adapt="nlms", **OPTS).offline_weights().tolist()
    assert [float(v) for v in logged[0][2:]] == fresh  # the first step gets no pair
    assert not np.allclose([float(v) for v in logged[2][2:]], comp.offline_weights().tolist())


CONDITIONED_DRIVER = r"""
#include <stdio.h>
#include "cd.h"

int main(void)
{
    static cd_state s;
    double x, c, m, a;
    cd_real cond[cd_N_CONDITIONS];
    cd_init(&s);
    while (scanf("%lf %lf %lf %lf", &x, &c, &m, &a) == 4) {
        cond[0] = (cd_real)c;
        printf("%.17g\n", (double)cd_step_adapt(&s, (cd_real)x, cond, (cd_real)m,
                                                (cd_real)a));
    }
    printf("%lld %lld %lld\n", (long long)cd_updates_count(&s),
           (long long)cd_skipped_count(&s), (long long)cd_refused_count(&s));
    return 0;
}
"""


@pytest.mark.parametrize("method", ["rls", "nlms"])
def test_a_conditioned_adaptive_step_equals_the_eager_one(tmp_path: Path, method: str) -> None:
    """PREFIX_step_adapt(s, desired, conditions, measured_prev, applied_prev) of a conditioned
    network: within 1e-12 of the eager compensator over 1500 samples (the condition ramped,
    a pair at every sample but the first), the counters equal; the guard set against the
    device (decreasing) so that updates are refused too."""
    net = conditioned_net()
    kw = {"direction": "decreasing", "input_range": (-2.5, 2.5), "limits": (-10.0, 10.0)}
    comp = AdaptiveCompensator(net, adapt=method, **kw)
    n = 1500
    x, c = signal(n, seed=3), np.linspace(0.0, 1.0, n)
    rows, us, y_prev, u_prev = [], [], np.nan, np.nan
    for t in range(n):
        rows.append((x[t], c[t], y_prev, u_prev))
        u = float(comp.step(torch.tensor([x[t]], dtype=D), torch.tensor([[c[t]]], dtype=D),
                            torch.tensor([y_prev], dtype=D), torch.tensor([u_prev], dtype=D)))
        us.append(u)
        y_prev, u_prev = 1.1 * x[t] + 0.01 * np.sin(t), u
    to_c(net, tmp_path, prefix="cd", adapt=method, **kw)
    header = (tmp_path / "cd.h").read_text()
    assert ("cd_real cd_step_adapt(cd_state *s, cd_real desired, const cd_real *conditions, "
            "cd_real measured_prev, cd_real applied_prev);") in header
    (tmp_path / "main.c").write_text(CONDITIONED_DRIVER)
    subprocess.run([CC, *FLAGS, "-I", str(tmp_path), "-o", str(tmp_path / "run"),
                    str(tmp_path / "main.c"), str(tmp_path / "cd.c"), "-lm"], check=True)
    text = "\n".join(" ".join(repr(float(v)) for v in row) for row in rows)
    out = subprocess.run([str(tmp_path / "run")], input=text, capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert gap([float(v) for v in out[:n]], us) <= 1e-12
    counts = [int(v) for v in out[n].split()]
    assert counts == [int(comp.updates_count()), int(comp.skipped_count()),
                      int(comp.refused_count())]
    assert counts[0] > 0 and counts[2] > 0, counts


@pytest.mark.slow
def test_the_adaptive_latency_benchmark_prints_its_rows() -> None:
    """benchmarks/latency.py --adaptive: twelve rows (2 models x 2 builds x 3 steps), the
    static rows' ratio 1, the adaptive rows' counters."""
    import sys

    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, str(root / "benchmarks" / "latency.py"), "--adaptive",
                          "--samples", "300", "--rounds", "1"], cwd=root, capture_output=True,
                         text=True, check=True, timeout=600).stdout
    rows = [line.split("|")[1:-1] for line in out.splitlines()
            if line.startswith("| ") and not line.startswith("| compensator")]
    assert len(rows) == 12, out
    for row in rows:
        cells = [c.strip() for c in row]
        assert (cells[5] == "1.00") == (cells[2] == "static"), cells
        assert cells[2] == "static" or int(cells[6].split(" / ")[0]) > 0, cells


@pytest.mark.parametrize(("kw", "name"), [({"adapt": "kalman"}, "adapt"),
                                          ({"adapt": "nlms", "nlms_step": 0.0}, "nlms_step"),
                                          ({"adapt": "rls", "forgetting": 1.5}, "forgetting")])
def test_bad_adaptive_options_name_the_argument(tmp_path: Path, kw: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        to_c(pi_inverse(), tmp_path, **OPTS, **kw)
    assert not list(tmp_path.iterdir())  # nothing written
