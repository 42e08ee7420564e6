"""``torchhys export --fleet ROOT/fleet_N``: every identified device of a ``torchhys fleet``
exported in one command (:func:`torchhys.deploy.export_fleet.export_fleet`).

    torchhys export --fleet ROOT/fleet_N --format c|onnx|torchscript|fmu --out DIR
        [--shared | --no-shared] [--prefix NAME] [--dtype float64|float32] [--limits LOW HIGH]
        [--input-margin M] [--direction D] [--initial-command U] [--fmi 2|3] [--step-size S]
        [--sample-period T] [--import MODULE] [--import-path DIR] [--force]

``--out`` is a folder (made where its parent exists). ``--format c`` writes one step shared
by every device (``NAME.h``, ``NAME.c``, ``NAME_params.c``) where the devices chose one
structure, else one pair ``NAME_<device>.h``/``.c`` a device, and says why in one line;
``--shared`` requires the shared step, ``--no-shared`` asks for the pairs. The other
formats write ``<device>.onnx``, ``<device>.pt`` or ``<device>.fmu``. The devices that
failed in ``fleet.csv`` (or have no checkpoint) are skipped and listed.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

import torch

from torchhys.checkpoints import read_checkpoint
from torchhys.cli.errors import report_user_error
from torchhys.cli.plugins import import_modules
from torchhys.deploy.c import DEFAULT_PREFIX
from torchhys.deploy.export_fleet import FORMATS, export_fleet, read_fleet

__all__ = ["fleet_main"]

_DTYPES = {"float64": torch.float64, "float32": torch.float32}


def _check(args: argparse.Namespace) -> None:
    """The options' combinations, before anything is read."""
    if args.ckpt is not None:
        raise ValueError("--fleet and --ckpt exclude each other: give one")
    if args.format not in FORMATS:
        raise ValueError(f"--format {args.format}: --fleet exports {', '.join(FORMATS)}")
    if args.shared is not None and args.format != "c":
        raise ValueError(f"--{'' if args.shared else 'no-'}shared applies to --format c only, "
                         f"not {args.format}")
    if args.prefix is not None and args.format not in ("c", "fmu"):
        raise ValueError(f"--prefix applies to --format c or fmu, not {args.format}")
    if args.adapt != "none":
        raise ValueError("--adapt applies to one --ckpt, not --fleet (a fleet's export is "
                         "static)")
    if args.format != "fmu":
        given = [f for f, v in (("--fmi", args.fmi), ("--step-size", args.step_size),
                                ("--sample-period", args.sample_period)) if v is not None]
        if given:
            raise ValueError(f"{given[0]} applies to --format fmu only, not {args.format}")
    if args.out.exists() and not args.out.is_dir():
        raise ValueError(f"--out {args.out}: not a folder (--fleet writes a folder of files)")
    if not args.out.exists():
        if not args.out.parent.is_dir():
            raise ValueError(f"--out {args.out}: its folder {args.out.parent} does not exist")
        args.out.mkdir()


def fleet_main(args: argparse.Namespace,
               checked_net: Callable[[dict[str, Any], str, str | None], torch.nn.Module]
               ) -> int:
    """Run ``torchhys export --fleet`` on the parsed options of ``torchhys export``
    (``checked_net``: its :func:`torchhys.cli.export.checked_net`, each device's network
    built and checked as one ``--ckpt``'s is); the exit status (0 ok, 2 a user error,
    printed as one line)."""
    try:
        _check(args)
        import_modules(args.imports, args.import_paths)  # the devices' plugin operators
        fleet = read_fleet(args.fleet, what="--fleet")
        dtype = None if args.dtype is None else _DTYPES[args.dtype]
        models = {}
        for name, path in fleet.checkpoints.items():
            what = f"--fleet: device {name!r} ({path})"
            models[name] = checked_net(read_checkpoint(path, what, lightning=True), what,
                                       args.dtype)
        fmu = ({"fmi": args.fmi or 2, "step_size": args.step_size,
                "sample_period": args.sample_period} if args.format == "fmu" else {})
        done = export_fleet(models, args.out, format=args.format,
                            prefix=args.prefix or DEFAULT_PREFIX, shared=args.shared,
                            dtype=dtype, overwrite=args.force, limits=args.limits,
                            initial_command=args.initial_command,
                            input_margin=args.input_margin, direction=args.direction, **fmu)
    except Exception as e:
        if not report_user_error("torchhys export", e, args.traceback):
            raise
        return 2
    n = len(done.devices)
    if done.shared:
        print(f"wrote {', '.join(str(p) for p in done.files)}: one C step shared by {n} "
              f"devices, a {args.prefix or DEFAULT_PREFIX}_params each")
    else:
        print(f"wrote {len(done.files)} files into {args.out} ({args.format}): one "
              f"{'pair' if args.format == 'c' else 'file'} for each of {n} devices")
        if done.reason:
            print(f"one pair of C files per device, not a shared step: {done.reason}")
    if fleet.skipped:
        print(f"skipped {len(fleet.skipped)} device(s): " + "; ".join(
            f"{k} ({v[:80]})" for k, v in fleet.skipped.items()))
    return 0
