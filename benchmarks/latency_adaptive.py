"""The C step's cost with online adaptation: static against adaptive RLS and NLMS
(:func:`torchhys.deploy.c.to_c` with ``adapt``), for the same models.

    python benchmarks/latency.py --adaptive [--samples 5000] [--rounds 5]
    python -m benchmarks.latency_adaptive [--samples 5000] [--rounds 5]

Two models with an affine readout: a 12-play network with an EIHO beside the plays and an
identity readout (14 weights), and a Prandtl-Ishlinskii inverse of 20 plays (22 weights).
Each is written three times, static (``PREFIX_step``), ``adapt="rls"`` and ``adapt="nlms"``
(``PREFIX_step_adapt``), and timed by a C harness (``cc -std=c99 -O2``, and ``-O3
-march=native``) that times each step with ``clock_gettime(CLOCK_MONOTONIC)`` after a warm-up
pass, as :mod:`benchmarks.latency`'s C rows. The adaptive steps get a pair at every sample:
the last command and a measured response 2 % above the last desired output (plus 0.01), so
that most updates are applied (their counts are printed). Rows interleaved over
``--rounds``; the table gives the median of the round medians (range) and the ratio of each
adaptive row's median to the static one's.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import tempfile
from pathlib import Path

import torch

from torchhys import EIHO, Backlash, InverseHysteresisNet, PrandtlIshlinskii

#: the adaptive timer's main (after benchmarks.latency.C_PRELUDE: the includes, cmp, now_ns)
C_TIMER_ADAPT_MAIN = r"""
/* timer REF.bin: the adaptive step over the reference (binary doubles), the pair of each
   sample the last command and 1.02 times the last desired output plus 0.01; once untimed,
   then from a fresh state timing every step; prints median_us, p99_us and the counters */
int main(int argc, char **argv)
{
    FILE *in;
    long n, i;
    double *x, *t, t0, sink = 0;
    comp_real u = 0, y = 0;
    comp_state s;
    int pass;
    if (argc != 2 || !(in = fopen(argv[1], "rb")))
        return 2;
    fseek(in, 0, SEEK_END);
    n = ftell(in) / (long)sizeof(double);
    rewind(in);
    x = malloc((size_t)n * sizeof *x);
    t = malloc((size_t)n * sizeof *t);
    if (!x || !t || fread(x, sizeof *x, (size_t)n, in) != (size_t)n)
        return 3;
    for (pass = 0; pass < 2; ++pass) {
        comp_init(&s);
        u = 0;
        y = 0;
        for (i = 0; i < n; ++i) {
            t0 = now_ns();
            u = comp_step_adapt(&s, (comp_real)x[i], i ? y : (comp_real)0.0 / 0.0, u);
            t[i] = now_ns() - t0;
            sink += (double)u;
            y = (comp_real)(1.02 * x[i] + 0.01);
        }
    }
    qsort(t, (size_t)n, sizeof *t, cmp);
    printf("median_us %.4f p99_us %.4f updates %lld skipped %lld refused %lld sink %g\n",
           t[n / 2] / 1e3, t[(long)(0.99 * n)] / 1e3, (long long)comp_updates_count(&s),
           (long long)comp_skipped_count(&s), (long long)comp_refused_count(&s), sink);
    return 0;
}
"""

FLAGS = {"cc -O2": ["-O2"], "cc -O3 -march=native": ["-O3", "-march=native"]}
LIMITS = (-10.0, 10.0)


def models() -> dict[str, tuple[torch.nn.Module, dict]]:
    """The two models and their export options (float64; the network's weights seeded)."""
    torch.manual_seed(0)
    t = torch.linspace(0, 60, 2000, dtype=torch.float64)
    y = 2.0 * torch.sin(t) * torch.exp(-t / 60)
    net = InverseHysteresisNet([EIHO(a=0.5, rule="recent", output="branch"),
                                Backlash(torch.linspace(0.0, 1.8, 12))], hidden=1,
                               activation="identity").double()
    net.fit_normalization(y, y / 2)
    widths = torch.linspace(0.0, 1.9, 20, dtype=torch.float64)
    pi = PrandtlIshlinskii(widths, torch.linspace(0.5, 0.05, 20, dtype=torch.float64),
                           linear_weight=0.3).inverse()
    return {"EIHO + 12 plays, identity readout": (net, {"limits": LIMITS}),
            "PI inverse, 20 plays": (pi, {"limits": LIMITS, "input_range": (-2.5, 2.5)})}


def build(model: torch.nn.Module, options: dict, adapt: str, folder: Path,
          flags: list[str]) -> Path:
    """The C step (prefix ``comp``) in its timer, compiled with ``cc -std=c99 FLAGS``."""
    from benchmarks.latency import C_PRELUDE, C_TIMER
    from torchhys.deploy.c import to_c

    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / "comp.c").exists():
        to_c(model, folder, prefix="comp", adapt=adapt, direction="increasing", **options)
        (folder / "timer.c").write_text(
            C_TIMER if adapt == "none" else C_PRELUDE + C_TIMER_ADAPT_MAIN)
    exe = folder / ("timer" + "".join(flags).replace("=", "_").replace("-", "_"))
    subprocess.run([os.environ.get("CC", "cc"), "-std=c99", *flags, "-I", str(folder), "-o",
                    str(exe), str(folder / "timer.c"), str(folder / "comp.c"), "-lm"],
                   check=True)
    return exe


def run(exe: Path, ref: Path) -> dict[str, float]:
    fields = subprocess.run([str(exe), str(ref)], capture_output=True, text=True,
                            check=True).stdout.split()
    return {k: float(v) for k, v in zip(fields[::2], fields[1::2], strict=False)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=5000)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    if args.samples < 200 or args.rounds < 1:
        parser.error("--samples must be at least 200, --rounds at least 1")
    t = torch.linspace(0, 100, args.samples, dtype=torch.float64)
    x = 1.8 * torch.sin(t) * torch.cos(0.13 * t)
    with tempfile.TemporaryDirectory() as name:
        tmp = Path(name)
        ref = tmp / "ref.bin"
        ref.write_bytes(x.numpy().tobytes())
        rows = []
        for k, (model_name, (model, options)) in enumerate(models().items()):
            for path, flags in FLAGS.items():
                for adapt in ("none", "rls", "nlms"):
                    exe = build(model, options, adapt, tmp / f"m{k}{adapt}", flags)
                    rows.append((model_name, path, adapt, exe))
        results: list[list[dict[str, float]]] = [[] for _ in rows]
        for _ in range(args.rounds):
            for j, (_, _, _, exe) in enumerate(rows):
                results[j].append(run(exe, ref))
    print(f"\n{args.samples} steps, batch 1, float64; {args.rounds} interleaved rounds: "
          "median of the round medians (range), median of the round p99s, the ratio of "
          f"the medians to the static step's; load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} CPUs\n")
    print("| compensator | C build | step | median (us) | p99 (us) | over static | "
          "updates / skipped / refused |")
    print("|---|---|---|---|---|---|---|")
    static: dict[tuple[str, str], float] = {}
    for (model_name, path, adapt, _), res in zip(rows, results, strict=True):
        meds = sorted(r["median_us"] for r in res)
        med, p99 = meds[len(meds) // 2], sorted(r["p99_us"] for r in res)[len(res) // 2]
        if adapt == "none":
            static[model_name, path] = med
        ratio = med / static[model_name, path]
        counts = ("" if adapt == "none" else
                  f"{res[0]['updates']:.0f} / {res[0]['skipped']:.0f} / "
                  f"{res[0]['refused']:.0f}")
        print(f"| {model_name} | {path} | {'static' if adapt == 'none' else adapt.upper()} | "
              f"{med:.3f} ({meds[0]:.3f} to {meds[-1]:.3f}) | {p99:.3f} | {ratio:.2f} | "
              f"{counts} |")


if __name__ == "__main__":
    main()
