"""``torchhys export``: a trained checkpoint to a deployable compensator file.

    torchhys export --ckpt CKPT --format torchscript|aoti|c|onnx|fmu|casadi --out FILE|DIR
    torchhys export --fleet ROOT/fleet_N --format c|onnx|torchscript|fmu --out DIR [--shared]
        [--limits LOW HIGH] [--input-margin M | --input-margin none]
        [--direction auto|increasing|decreasing|none] [--dtype float64|float32]
        [--prefix NAME] [--fmi 2|3] [--step-size S] [--sample-period T] [--force]
        [--adapt none|rls|nlms [--forgetting F] [--adapt-bound B] [--dead-zone D]
         [--excitation E] [--nlms-step S] [--initial-covariance P]]
        [--config FILE] [--print_config]

``--format c`` writes ``DIR/NAME.h`` and ``DIR/NAME.c`` (``--prefix``, default
``torchhys_comp``), dependency-free C99 (:func:`torchhys.deploy.c.to_c`); ``--dtype`` sets
the exported step's real type (default: the checkpoint's).

``--format fmu`` writes ``NAME.fmu`` (``--out``, ending in ``.fmu``), a co-simulation FMU
(``--fmi 2``, the default, or ``3``) whose binary is that C step
(:func:`torchhys.deploy.export_fmu.to_fmu`): ``--prefix`` is its model identifier (default
the file's stem), ``--sample-period`` the compensator's sample period in s and
``--step-size`` the default communication step, an integer multiple of it (each defaults to
the other, both to 1 s).

``--fleet ROOT/fleet_N`` (instead of ``--ckpt``) exports every identified device of a
``torchhys fleet``, one file a device into the folder ``--out``, or with ``--format c`` one
step shared by them all with a table of each device's constants
(:mod:`torchhys.cli.export_fleet`).

``--format casadi`` writes ``NAME.casadi`` (``--out``, ending in ``.casadi``), the step as a
CasADi function ``(x, state) -> (u, new_state)`` saved by ``casadi.Function.save``
(:func:`torchhys.deploy.export_casadi.to_casadi`; ``--prefix``: the function's name, default
``torchhys_comp``); it needs the casadi extra and has no adaptive form.

The options are also spelled as ``torchhys fit`` spells them: with underscores
(``--ckpt_path``, ``--input_margin``), from a YAML file of them (``--config FILE``, the
command line's own options overriding it) and printed as one (``--print_config``).

The output is checked before anything is read or compiled: its folder exists and is
writable, it is not the ``--ckpt`` file itself (refused even with ``--force``), and an
existing file is replaced only with ``--force``. Every file is written atomically (a
temporary file beside it, flushed, renamed over it; the C pair both complete before either
is renamed): on an error, a full disk included, the previous output is left whole.
Numbers may be given in scientific notation, negative ones too (``--limits -5e-3 5e-3``).

The compensator clamps its input to the training input range widened by ``--input-margin``
(a share of the range, default 0.05) and counts the samples it clamped; its command never
moves against the direction of the target's trend in the training data (``--direction``):
see :class:`torchhys.deploy.streaming.StreamingCompensator`.

``--adapt rls`` or ``nlms`` exports the adaptive compensator
(:class:`torchhys.deploy.adaptive.AdaptiveCompensator`, every format): its step also takes
the last sample's measured response and applied command and moves the readout's weights
(``--forgetting``, ``--adapt-bound``, ``--dead-zone``, ``--excitation``, ``--nlms-step``,
``--initial-covariance``: its options). A model without an affine readout is refused.

CKPT is a checkpoint of :class:`torchhys.training.InverseHysteresisModule` (Lightning's
``{"state_dict": {"net.*": ...}, "hyper_parameters": {...}}``; the network is rebuilt from
``operator``, ``hidden``, ``activation`` and ``operator_kwargs``) or a plain ``torch.save``d
state dict of an :class:`torchhys.InverseHysteresisNet` (then give ``--operator``,
``--hidden``, ``--activation`` and ``--operator-kwargs`` as it was built). Loaded with
``weights_only=True``: no code from the file is run. The checkpoint is read as a spec plus
weights, without Lightning: ``torchhys export`` runs without the ``train`` extra.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path

import torch

from torchhys import InverseHysteresisNet
from torchhys._finite import check_output, check_weights
from torchhys._memory import check_memory, format_bytes
from torchhys.checkpoints import read_checkpoint
from torchhys.cli.errors import config_errors, report_user_error
from torchhys.cli.export_fleet import fleet_main
from torchhys.cli.negative_numbers import accept_negative_numbers
from torchhys.cli.options_file import parse
from torchhys.cli.plain_text import plain
from torchhys.cli.plugins import import_modules
from torchhys.compose import Composed
from torchhys.compose.spec import build_composed, is_composed_spec
from torchhys.deploy.c import DEFAULT_PREFIX, check_prefix, to_c
from torchhys.deploy.export import ADAPT_DEFAULTS, to_aoti, to_torchscript
from torchhys.deploy.export_casadi import save_casadi, to_casadi
from torchhys.deploy.export_fmu import periods, to_fmu
from torchhys.deploy.export_onnx import to_onnx
from torchhys.deploy.ranges import DIRECTIONS
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.identification.specs import build_operators

__all__ = ["build_net", "main"]

_ARCH_KEYS = ("operator", "hidden", "activation", "operator_kwargs", "n_conditions",
              "condition_degree")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="torchhys export",
                                description=plain(__doc__.splitlines()[0]))
    accept_negative_numbers(p)  # --limits -5e-3 5e-3
    p.add_argument("--ckpt", type=Path, required=True, help="checkpoint or state dict file")
    p.add_argument("--fleet", type=Path, default=None, metavar="DIR",
                   help="instead of --ckpt: every identified device of a torchhys fleet "
                        "folder (ROOT/fleet_N), into the folder --out (docs/fleet.md)")
    p.add_argument("--shared", action=argparse.BooleanOptionalAction, default=None,
                   help="--fleet --format c: one C step shared by every device with a table "
                        "of each one's constants (default: where the devices allow it)")
    p.add_argument("--format", choices=("torchscript", "aoti", "c", "onnx", "fmu", "casadi"),
                   required=True, help="the file's kind: TorchScript (.pt), AOTInductor "
                   "(.pt2), C sources (a folder), ONNX (.onnx), an FMU (.fmu), CasADi (.casadi)")
    p.add_argument("--out", type=Path, required=True,
                   help="output file (.pt, .pt2, .onnx or .fmu), or with --format c an "
                        "existing folder")
    p.add_argument("--dtype", choices=tuple(_DTYPES), default=None,
                   help="the exported step's real type (default: the checkpoint's)")
    p.add_argument("--prefix", type=_prefix, default=None,
                   help=f"--format c: the files' name and the C names' prefix (default "
                        f"{DEFAULT_PREFIX}); --format fmu: the model identifier (default the "
                        "--out file's stem)")
    fmu = p.add_argument_group("--format fmu")
    fmu.add_argument("--fmi", type=int, choices=(2, 3), default=None,
                     help="the FMI version (default 2)")
    fmu.add_argument("--step-size", type=_positive, default=None, metavar="S",
                     help="the default communication step in s, an integer multiple of the "
                          "sample period (default the sample period)")
    fmu.add_argument("--sample-period", type=_positive, default=None, metavar="T",
                     help="the compensator's sample period in s (default the step size, "
                          "or 1)")
    p.add_argument("--limits", type=float, nargs=2, metavar=("LOW", "HIGH"),
                   help="command saturation (default: the training output range)")
    p.add_argument("--initial-command", type=float, default=0.0,
                   help="command held until the first finite input (default 0)")
    p.add_argument("--input-margin", type=_margin, default=0.05, metavar="M",
                   help="clamp the input to the training input range widened by this share "
                        "of it on each side (default 0.05); 'none': no clamp")
    p.add_argument("--direction", choices=DIRECTIONS, default="auto",
                   help="the command never moves against this direction of the input "
                        "(default auto: the training data's; none: no guard)")
    adapt = p.add_argument_group("online adaptation of the readout (--adapt rls or nlms)")
    adapt.add_argument("--adapt", choices=("none", "rls", "nlms"), default="none",
                       help="adapt the readout's weights online from the measured response "
                            "(default none: the static compensator)")
    for flag, text in _ADAPT_FLAGS.items():
        name = flag[2:].replace("-", "_")
        adapt.add_argument(flag, type=float, default=ADAPT_DEFAULTS[name],
                           help=f"{text} (default {ADAPT_DEFAULTS[name]})")
    p.add_argument("--import", dest="imports", action="append", default=[], metavar="MODULE",
                   help="import this module first (repeatable): the operators it registers "
                        "can be named in the checkpoint's config")
    p.add_argument("--import-path", dest="import_paths", action="append", default=[],
                   metavar="DIR", help="a folder to search for the modules of --import "
                   "(repeatable; the working folder is not searched unless named: "
                   "--import-path .)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing output file (never the --ckpt file itself)")
    p.add_argument("--traceback", action="store_true",
                   help="on an error in the checkpoint or options, show the traceback "
                        "(also TORCHHYS_TRACEBACK=1)")
    arch = p.add_argument_group("architecture of a plain state dict")
    arch.add_argument("--operator", help='e.g. eiho, zhao_tan, none, or a JSON list of names '
                      'and specs such as {"fit": "pi_ls", "n_widths": 30}')
    arch.add_argument("--hidden", type=int)
    arch.add_argument("--activation")
    arch.add_argument("--operator-kwargs", help="JSON object, e.g. '{\"rule\": \"dominant\"}'")
    return p


_DTYPES = {"float64": torch.float64, "float32": torch.float32}
#: the adaptive compensator's options on the command line
_ADAPT_FLAGS = {
    "--forgetting": "RLS's forgetting factor, in (0, 1]",
    "--adapt-bound": "the weights' box about the offline fit, a share of their scale (>= 0)",
    "--dead-zone": "no update while the prediction error is within this (command units)",
    "--excitation": "no update until the normalized regressors moved by more than this",
    "--nlms-step": "NLMS's step size, in (0, 1]",
    "--initial-covariance": "RLS's initial covariance of the normalized weights (> 0)",
}


def _adapt_options(args: argparse.Namespace) -> dict:
    """The adaptive options of the command line ({} for --adapt none)."""
    if args.adapt == "none":
        return {}
    return {"adapt": args.adapt, **{f[2:].replace("-", "_"): getattr(args, f[2:].replace(
        "-", "_")) for f in _ADAPT_FLAGS}}


def _compensator(net: torch.nn.Module, options: dict, adapt: dict) -> StreamingCompensator:
    """The compensator of ``net``; an error in an adaptive option names its flag, a model
    without an affine readout names ``--adapt``."""
    try:
        return StreamingCompensator(net, **options, **adapt)
    except ValueError as err:
        text = str(err)
        for flag in _ADAPT_FLAGS:
            name = flag[2:].replace("-", "_")
            if adapt and text.startswith(name + " "):
                raise ValueError(flag + text[len(name):]) from None
        if adapt and text.startswith("model: its compensator head"):
            raise ValueError(f"--adapt {adapt['adapt']}: the checkpoint's model{text[5:]}"
                             ) from None
        raise


def _prefix(text: str) -> str:
    try:
        return check_prefix(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (value > 0 and value != float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def _margin(text: str) -> float | None:
    if text.strip().lower() == "none":
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a share of the input range (a number >= 0) or 'none', got {text!r}"
        ) from None
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0 or 'none', got {text!r}")
    return value


def _plain_arch(args: argparse.Namespace) -> dict:
    if args.hidden is None:
        raise ValueError(
            "the file holds a plain state dict: give --hidden (and --operator, --activation, "
            "--operator-kwargs as the network was built)"
        )
    operator = args.operator or "eiho"
    operator = None if operator == "none" else (
        json.loads(operator) if operator.startswith(("[", "{")) else operator)
    return {"operator": operator, "hidden": args.hidden,
            "activation": args.activation or "sigmoid",
            "operator_kwargs": json.loads(args.operator_kwargs or "{}")}


def _same_file(a: Path, b: Path) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)  # hard links
    except OSError:
        return False


def check_out(args: argparse.Namespace) -> list[Path]:
    """The files the export will write, after checking (before anything is read or
    compiled) that they can be written: the folder exists and is writable, no target is a
    folder or the ``--ckpt`` file, an existing target only with ``--force``."""
    if args.format == "c":
        if not args.out.is_dir():
            raise ValueError(f"--out {args.out}: the folder does not exist (--format c writes "
                             "two files into an existing folder)")
        folder, prefix = args.out, args.prefix or DEFAULT_PREFIX
        targets = [args.out / f"{prefix}.h", args.out / f"{prefix}.c"]
    else:
        folder, targets = args.out.parent, [args.out]
        if args.format in ("fmu", "casadi") and args.out.suffix != f".{args.format}":
            raise ValueError(f"--out {args.out} must end in .{args.format} "
                             f"(--format {args.format})")
        if args.out.is_dir():
            raise ValueError(f"--out {args.out} is a folder; --format {args.format} writes one "
                             "file: give its name")
        if not folder.is_dir():
            raise ValueError(f"--out {args.out}: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"--out {args.out}: the folder {folder} is not writable")
    for target in targets:
        if _same_file(target, args.ckpt):
            raise ValueError(f"--out {target} is the --ckpt file itself: the export would "
                             "replace its own checkpoint; give another --out")
        if target.is_dir():
            raise ValueError(f"--out {target} is a folder; move it or give another --out")
        if target.exists() and not args.force:
            raise ValueError(f"--out {target} exists; give --force to replace it, or "
                             "another --out")
    return targets


def check_size(arch: dict, state: dict) -> None:
    """Refuse, before building it, a network whose layers the architecture ``arch`` sizes
    beyond the weights ``state`` holds (a damaged or crafted checkpoint: ``hidden: 10**9``
    in a 1 KB file) or beyond the memory limit (``TORCHHYS_MAX_MEMORY``,
    :mod:`torchhys._memory`)."""
    hidden = arch.get("hidden")
    if not isinstance(hidden, int) or isinstance(hidden, bool) or hidden < 1:
        return  # InverseHysteresisNet's own check names it
    weight = state.get("hidden.weight")
    shaped = isinstance(weight, torch.Tensor) and weight.dim() == 2
    features = int(weight.shape[1]) if shaped else 1
    itemsize = weight.element_size() if shaped and weight.is_floating_point() else 4
    params = hidden * (features + 2) + 1  # the hidden and output layers
    nbytes = params * 4 + (params * itemsize if itemsize != 4 else 0)  # built, converted
    held = sum(v.numel() for v in state.values() if isinstance(v, torch.Tensor))
    if params > held:
        raise ValueError(
            f"the architecture (hidden={hidden}, {features} input features) asks for {params} "
            f"weights ({format_bytes(nbytes)}), but the file holds {held} values in all: its "
            "hyper_parameters (or --hidden) do not describe its weights (a damaged or "
            "mismatched checkpoint)")
    check_memory(nbytes, f"the network of hidden={hidden} ({features} input features)",
                 "check the checkpoint's hyper_parameters (or --hidden)")


def checked_net(ckpt: dict, what: str, dtype: str | None = None,
                arch: dict | None = None) -> torch.nn.Module:
    """:func:`build_net`, then its weights checked finite and its output on a sweep not
    overflowing (a diverged fit's: :mod:`torchhys._finite`, naming ``what``), in ``dtype``
    (``"float64"``, ``"float32"``; None: as saved). A TypeError is a user error."""
    with config_errors():
        net = build_net(ckpt, arch)
        check_weights(net, what)  # a diverged fit's NaN weights
        if isinstance(net, (InverseHysteresisNet, Composed)):
            check_output(net, what)  # or its overflowing ones
        return net if dtype is None else net.to(_DTYPES[dtype])


def build_net(ckpt: dict, arch: dict | None = None) -> torch.nn.Module:
    """Rebuild the network of a Lightning checkpoint (or of a plain state dict + ``arch``),
    after :func:`check_size`; a composed model from its spec (``hyper_parameters["net"]``:
    :func:`torchhys.compose.spec.build_composed`)."""
    if "state_dict" in ckpt:
        hp = ckpt.get("hyper_parameters") or {}
        if is_composed_spec(hp.get("net")):
            state = {k[4:]: v for k, v in ckpt["state_dict"].items() if k.startswith("net.")}
            return build_composed(hp["net"], state, "the checkpoint's model.net")
        if "net" in hp:
            raise ValueError("the checkpoint's model (a sequence model) was passed in built, "
                             "without its class in hyper_parameters: export it from Python "
                             "(torchhys.deploy.export, torchhys.deploy.c.to_c), or fit it from "
                             "a config whose model.net names its class (docs/composing.md)")
        missing = [k for k in ("operator", "hidden") if k not in hp]
        if missing:
            raise ValueError(
                f"the checkpoint's hyper_parameters lack {missing}: the network was passed in "
                "ready-made; export it from Python with torchhys.deploy.export instead"
            )
        arch = {k: hp.get(k) for k in _ARCH_KEYS}
        state = {k[4:]: v for k, v in ckpt["state_dict"].items() if k.startswith("net.")}
    elif arch is None:
        raise ValueError("a plain state dict needs the architecture (see --hidden)")
    else:
        state = ckpt
    check_size(arch, state)
    # operator specs as the training module reads them (names, {"name": ...} and
    # {"fit": ...} dicts); the fitted families get their widths and weights from the state
    try:  # sizes that no estimate covers (a registered operator's n_states, n, ...)
        operators, _ = build_operators(arch["operator"], arch.get("operator_kwargs") or {})
        degree = arch.get("condition_degree")
        net = InverseHysteresisNet(
            operators, arch["hidden"], activation=arch.get("activation") or "sigmoid",
            n_conditions=(arch.get("n_conditions") or 0) if degree is not None else 0,
            condition_degree=degree if degree is not None else 1,
        )
    except (MemoryError, RuntimeError) as err:
        if isinstance(err, RuntimeError) and "allocate" not in str(err):
            raise
        asked = re.search(r"allocate (\d+) bytes", str(err))
        size = f" ({format_bytes(int(asked.group(1)))} at once)" if asked else ""
        raise ValueError(f"the network of the operators {arch['operator']!r} cannot be built: "
                         f"out of memory{size}; check the sizes in the checkpoint's "
                         "hyper_parameters (a damaged or crafted checkpoint)") from None
    ref = next(iter(state.values()), None)
    if isinstance(ref, torch.Tensor) and ref.is_floating_point():
        net = net.to(ref.dtype)  # before loading: float64 weights are not rounded to float32
    try:
        net.load_state_dict(state)
    except RuntimeError as err:  # missing, unexpected or mis-shaped weights
        raise ValueError(f"the weights do not fit the network {arch}: {err}") from None
    return net


def main(argv: list[str]) -> int:
    """Run ``torchhys export``; returns the exit status (0 ok, 2 usage or input error).

    An error in the user's checkpoint or options is printed as one line,
    ``torchhys export: error: <message>`` (``--traceback``: raised instead); any other
    exception is a bug and propagates (:mod:`torchhys.cli.errors`).
    """
    parser = _parser()
    if any(a == "--fleet" or a.startswith("--fleet=") for a in argv):
        parser._option_string_actions["--ckpt"].required = False  # its own option's folder
    args = parse(parser, argv, {"--ckpt_path": "--ckpt", "--ckpt-path": "--ckpt"})
    if args.fleet is not None:
        return fleet_main(args, checked_net)
    try:
        if args.shared is not None:
            raise ValueError(f"--{'' if args.shared else 'no-'}shared applies to --fleet only")
        if args.prefix is not None and args.format not in ("c", "fmu", "casadi"):
            raise ValueError(f"--prefix applies to --format c only (or fmu: the model "
                             f"identifier, casadi: the function's name), not {args.format}")
        if args.format == "casadi" and args.adapt != "none":
            raise ValueError("--adapt applies to the torchscript, aoti, c, onnx and fmu "
                             "formats, not casadi (its function has no adaptive form)")
        fmu = _fmu_options(args)
        check_out(args)
        import_modules(args.imports, args.import_paths)
        ckpt = read_checkpoint(args.ckpt, "--ckpt", lightning=False)
        options = {"limits": args.limits, "initial_command": args.initial_command,
                   "input_margin": args.input_margin, "direction": args.direction}
        with config_errors():  # a TypeError here is in the options or the checkpoint
            net = checked_net(ckpt, f"--ckpt {args.ckpt}", args.dtype,
                              None if "state_dict" in ckpt else _plain_arch(args))
            adapt = _adapt_options(args)
            comp = _compensator(net, options, adapt)
        if args.format == "c":  # the adaptive keywords only when adapting
            written = to_c(net, args.out, prefix=args.prefix or DEFAULT_PREFIX,
                           dtype=comp.low.dtype, **options, **adapt)
            args.out = " and ".join(str(p) for p in written)
        elif args.format == "fmu":
            to_fmu(net, args.out, dtype=comp.low.dtype, **fmu, **options, **adapt)
            args.out = f"{args.out} (FMI {fmu['fmi']}.0, model identifier {fmu['prefix']})"
        elif args.format == "casadi":
            try:
                fn = to_casadi(net, dtype=comp.low.dtype, name=args.prefix or DEFAULT_PREFIX,
                               **options)
            except ImportError as err:  # the casadi extra is missing: one line, a user error
                raise ValueError(str(err)) from None
            save_casadi(fn, args.out)
        elif args.format == "onnx":
            try:
                to_onnx(comp, args.out)
            except ImportError as err:  # the onnx extra is missing: one line, a user error
                raise ValueError(str(err)) from None
        else:
            export = to_torchscript if args.format == "torchscript" else to_aoti
            export(comp, args.out)
    except Exception as e:
        if not report_user_error("torchhys export", e, args.traceback):
            raise
        return 2
    clamp = (f"input clamped to [{float(comp.in_low):.6g}, {float(comp.in_high):.6g}]"
             if comp.clamp_input else "input not clamped")
    if comp.n_conditions:
        bounds = ", ".join(f"[{float(a):.6g}, {float(b):.6g}]"
                           for a, b in zip(comp.cond_low, comp.cond_high, strict=True))
        clamp += (f", {comp.n_conditions} condition(s) clamped to {bounds}"
                  if comp.clamp_conditions else f", {comp.n_conditions} condition(s)")
    guard = {1: "increasing", -1: "decreasing", 0: "none"}[int(comp.direction)]
    dtype = str(comp.low.dtype).replace("torch.", "")
    print(f"wrote {args.out} ({args.format}, {dtype}); command limits [{float(comp.low):.6g}, "
          f"{float(comp.high):.6g}], {clamp}, direction {guard}{_adapt_report(args)}")
    return 0


def _fmu_options(args: argparse.Namespace) -> dict:
    """The FMU's options of the command line, checked ({} but for --format fmu, where the
    FMU's flags are refused)."""
    given = [f for f, v in (("--fmi", args.fmi), ("--step-size", args.step_size),
                            ("--sample-period", args.sample_period)) if v is not None]
    if args.format != "fmu":
        if given:
            raise ValueError(f"{given[0]} applies to --format fmu only, not {args.format}")
        return {}
    prefix = args.prefix or args.out.stem
    try:
        check_prefix(prefix)
    except ValueError as err:
        flag = "--prefix" if args.prefix else f"--out {args.out}: the file's stem (give --prefix)"
        raise ValueError(f"{flag}: {err}") from None
    step, period = periods(args.step_size, args.sample_period, ("--step-size", "--sample-period"))
    return {"fmi": args.fmi or 2, "prefix": prefix, "step_size": step, "sample_period": period}


def _adapt_report(args: argparse.Namespace) -> str:
    """The report's words on the adaptation ("" without)."""
    if args.adapt == "none":
        return ""
    rate = (f"forgetting {args.forgetting:.6g}" if args.adapt == "rls"
            else f"step {args.nlms_step:.6g}")
    return f", adaptation {args.adapt} ({rate}, bound {args.adapt_bound:.6g})"


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
