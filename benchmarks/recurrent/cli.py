"""The command line of ``python -m benchmarks.recurrent``."""

from __future__ import annotations

import argparse
import time

import torch

from . import accuracy, latency


def main(argv: list[str] | None = None) -> dict:
    """Run the parts asked for and print their markdown tables; returns their results."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.recurrent",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("parts", nargs="*", choices=("accuracy", "latency"),
                        help="what to run (default: both)")
    parser.add_argument("--quick", action="store_true",
                        help="a few training steps, one seed, small windows; the 16-unit "
                             "layers only and short timings (a smoke test)")
    parser.add_argument("--data", nargs="+", default=["bouc_wen", *accuracy.REAL],
                        help="'bouc_wen' and/or protocols of benchmarks/real_data")
    parser.add_argument("--models", nargs="+", choices=tuple(accuracy.MODELS),
                        default=list(accuracy.MODELS), metavar="LABEL",
                        help=f"trained rows (default all: {', '.join(accuracy.MODELS)})")
    parser.add_argument("--rtneural", metavar="DIR",
                        help="an RTNeural checkout (default: $RTNEURAL_DIR)")
    parser.add_argument("--sizes", nargs="+", type=int, default=None,
                        help=f"hidden sizes timed (default {latency.SIZES})")
    args = parser.parse_args(argv)
    parts = args.parts or ["accuracy", "latency"]
    for name in args.data if "accuracy" in parts else ():  # before any training
        if name != "bouc_wen" and name not in accuracy.DATASETS:
            parser.error(f"--data: expected 'bouc_wen' or a protocol of "
                         f"benchmarks/real_data, got {name!r}")
    torch.set_num_threads(1)
    out: dict = {}
    if "accuracy" in parts:
        budget = accuracy.QUICK_BUDGET if args.quick else accuracy.FULL
        start = time.perf_counter()
        out["accuracy"] = accuracy.run(args.data, budget, args.models,
                                       lambda s: print(s, flush=True))
        print(f"\naccuracy: {time.perf_counter() - start:.0f} s; budget {budget}\n")
        for name, rows in out["accuracy"].items():
            print(accuracy.markdown(name, rows) + "\n")
    if "latency" in parts:
        sizes = args.sizes or ((16,) if args.quick else latency.SIZES)
        timing = ({"steps": 2000, "rounds": 3, "repeats": 1, "flags": {"-O2": ("-O2",)}}
                  if args.quick else {})
        out["latency"] = latency.run(args.rtneural, sizes, **timing,
                                     log=lambda s: print(s, flush=True))
        print("\n" + latency.markdown(out["latency"]))
    return out
