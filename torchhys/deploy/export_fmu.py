"""Export a compensator as a co-simulation FMU (FMI 2.0 or 3.0) whose binary is the C99 step.

:func:`to_fmu` writes the C step (:func:`torchhys.deploy.c.to_c`), the FMI wrapper and the
model description (their parts: :mod:`torchhys.deploy.fmu`), compiles the binary and zips
the FMU; :func:`check_fmu` reads one back. ``docs/deployment.md`` ("FMU") describes the
variables, the timing and the import into other tools."""

from __future__ import annotations

import hashlib
import io
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import uuid
import zipfile
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

from torchhys._version import __version__
from torchhys.deploy.c import check_prefix, to_c
from torchhys.deploy.c._files import _describe
from torchhys.deploy.c._to_c import _build
from torchhys.deploy.export import ADAPT_DEFAULTS, write_outputs
from torchhys.deploy.fmu._core import core_source
from torchhys.deploy.fmu._fmi2 import FMI2
from torchhys.deploy.fmu._fmi2_unsupported import FMI2_UNSUPPORTED
from torchhys.deploy.fmu._fmi3 import FMI3
from torchhys.deploy.fmu._fmi3_unsupported import FMI3_UNSUPPORTED
from torchhys.deploy.fmu._variables import variables as variable_table
from torchhys.deploy.fmu._xml import build_description, model_description

#: the compiler's flags (the C export's, and a shared library's)
CFLAGS = ("-std=c99", "-O2", "-shared", "-fPIC", "-fvisibility=hidden")
#: the tolerance of "an integer multiple" (a share of the sample period)
MULTIPLE_TOLERANCE = 1e-9
__all__ = ["check_fmu", "to_fmu"]

_TOKEN_NAMESPACE = uuid.UUID("6f1d7f0e-4a8e-5b0c-9d52-74686873796d")  # torchhys FMUs


def _positive(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


def periods(step_size: float | None, sample_period: float | None,
            names: tuple[str, str] = ("step_size", "sample_period")) -> tuple[float, float]:
    """``(step_size, sample_period)`` checked: each positive and finite, the step an integer
    multiple of the sample period; one missing is the other, both missing 1 s. ``names``:
    the two arguments' names in the messages."""
    if step_size is not None:
        step_size = _positive(step_size, names[0])
    if sample_period is not None:
        sample_period = _positive(sample_period, names[1])
    sample_period = sample_period or step_size or 1.0
    step_size = step_size or sample_period
    ratio = step_size / sample_period
    if abs(ratio - round(ratio)) > MULTIPLE_TOLERANCE * max(1.0, ratio) or round(ratio) < 1:
        raise ValueError(f"{names[0]} {step_size!r} is not an integer multiple of the sample "
                         f"period ({names[1]}) {sample_period!r}: the FMU runs whole samples")
    return step_size, sample_period


def platform_folder(fmi: int) -> tuple[str, str]:
    """``(binaries/<folder>, suffix)`` of this machine's shared library, FMI 2's or 3's name."""
    machine = platform.machine().lower()
    arch = {"amd64": "x86_64", "x86_64": "x86_64", "aarch64": "aarch64", "arm64": "aarch64"
            }.get(machine)
    system = {"linux": "linux", "darwin": "darwin"}.get(sys.platform)
    if arch is None or system is None or (fmi == 2 and arch != "x86_64"):
        raise ValueError(f"binaries: no FMI {fmi} platform folder for {sys.platform} "
                         f"{machine} known here; give binaries=False (a sources-only FMU) and "
                         "build sources/ with the importing tool")
    suffix = ".so" if system == "linux" else ".dylib"
    return (f"{system}64" if fmi == 2 else f"{arch}-{system}"), suffix


_COMPILE_S = 600
"""Seconds the C compiler of an FMU's binary may take."""


def _compile(sources: dict[str, bytes], prefix: str, suffix: str) -> bytes:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise ValueError("binaries: no C compiler (cc or gcc) on PATH; give binaries=False "
                         "for a sources-only FMU")
    with tempfile.TemporaryDirectory(prefix="torchhys-fmu-") as tmp:
        folder = Path(tmp)
        for name, data in sources.items():
            (folder / name).write_bytes(data)
        out = folder / f"{prefix}{suffix}"
        cfiles = [str(folder / n) for n in sources if n.endswith(".c")]
        try:
            done = subprocess.run([cc, *CFLAGS, "-I", str(folder), "-o", str(out), *cfiles,
                                   "-lm"], capture_output=True, text=True, timeout=_COMPILE_S)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"the FMU's sources did not compile within {_COMPILE_S} s "
                               f"({cc}): the compiler was stopped") from None
        if done.returncode != 0:
            first = (done.stderr.strip().splitlines() or ["(no message)"])[0]
            raise RuntimeError(f"the FMU's sources did not compile ({cc}): {first}")
        return out.read_bytes()


def _check_path(path: object) -> Path:
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    out = Path(path)
    if out.suffix != ".fmu":
        raise ValueError(f"path {os.fspath(path)!r} must end in .fmu")
    if out.is_dir():
        raise ValueError(f"path {os.fspath(path)!r} is a folder")
    if not out.parent.is_dir():
        raise ValueError(f"path {os.fspath(path)!r}: the folder {out.parent} does not exist")
    return out


def _zip(entries: dict[str, bytes]) -> bytes:
    """The archive of ``entries`` (deterministic: fixed times, sorted folders first)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries.items():
            info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, data)
    return buf.getvalue()


def to_fmu(
    model: nn.Module, path: str | os.PathLike, *, fmi: int = 2, prefix: str | None = None,
    dtype: torch.dtype = torch.float64, step_size: float | None = None,
    sample_period: float | None = None, limits: tuple[float, float] | None = None,
    initial_command: float = 0.0, input_range: tuple[float, float] | None = None,
    input_margin: float | None = 0.05, direction: str = "auto", model_name: str | None = None,
    units: Mapping[str, str] | None = None, description: str | None = None,
    binaries: bool = True, adapt: str = "none",
    forgetting: float = ADAPT_DEFAULTS["forgetting"],
    adapt_bound: float = ADAPT_DEFAULTS["adapt_bound"],
    dead_zone: float = ADAPT_DEFAULTS["dead_zone"],
    excitation: float = ADAPT_DEFAULTS["excitation"],
    nlms_step: float = ADAPT_DEFAULTS["nlms_step"],
    initial_covariance: float = ADAPT_DEFAULTS["initial_covariance"],
) -> Path:
    """Write the compensator of ``model`` as a co-simulation FMU (FMI 2.0 or 3.0).

    The FMU's binary is the C99 step of :func:`torchhys.deploy.c.to_c` and a wrapper that
    runs it once a sample period: ``doStep`` over a communication step of ``n`` sample
    periods runs ``n`` samples with the inputs held; the output ``command`` is then the last
    sample's (a command read at ``t`` is that of the sample at ``t - sample_period``: no
    direct feedthrough, no algebraic loop). Variables (value references): ``desired`` (0,
    input), ``command`` (1, output), ``condition_k`` (2.., inputs, where the model has
    operating conditions), the constants ``command_low``, ``command_high``, ``input_low``,
    ``input_high`` (with the input clamp) and ``sample_period`` (compiled into the step:
    read-only), the outputs ``nonfinite_count`` and ``out_of_range_count`` and ``time``.
    With ``adapt`` ``"rls"`` or ``"nlms"`` (the adaptive step ``PREFIX_step_adapt``) also
    the inputs ``measured_prev`` and ``applied_prev`` (the last sample's pair: used by the
    first sample of a communication step, NaN for the others) and the outputs
    ``updates_count``, ``skipped_count`` and ``refused_count``.

    Args:
        model, dtype, limits, initial_command, input_range, input_margin, direction: as
            :func:`torchhys.deploy.c.to_c`.
        adapt, forgetting, adapt_bound, dead_zone, excitation, nlms_step,
            initial_covariance: the adaptive compensator's (defaults: those of
            :func:`torchhys.deploy.export.to_torchscript`).
        path: the ``.fmu`` file (its folder must exist); written atomically.
        fmi: 2 or 3.
        prefix: the model identifier (the C names' prefix and the binary's name; a C
            identifier); default ``path``'s stem.
        step_size: the default communication step (DefaultExperiment stepSize), an integer
            multiple of ``sample_period``; default the sample period.
        sample_period: the compensator's sample period in s; default ``step_size``, or 1.
        model_name: the model description's modelName (default the prefix).
        units: variable name -> unit (``desired``, ``command``, ``condition_k``, ...): the
            model records none.
        description: the model description's description (default: the model, its
            training range, the options and the torchhys version).
        binaries: compile ``binaries/<platform>/PREFIX.so`` here (``cc -std=c99 -O2 -shared
            -fPIC``); False: a sources-only FMU.

    Returns:
        ``path``.

    Raises:
        ValueError: a bad argument (named), no compiler with ``binaries=True``; see
            :func:`torchhys.deploy.c.to_c`.
        RuntimeError: the sources did not compile (the compiler's first line).
    """
    if fmi not in (2, 3) or isinstance(fmi, bool):
        raise ValueError(f"fmi must be 2 or 3, got {fmi!r}")
    out = _check_path(path)
    prefix = check_prefix(out.stem if prefix is None else prefix)
    step_size, sample_period = periods(step_size, sample_period)
    if model_name is not None and not (isinstance(model_name, str) and model_name.strip()):
        raise ValueError(f"model_name must be a non-empty string, got {model_name!r}")
    if units is not None and not isinstance(units, Mapping):
        raise TypeError(f"units must be a mapping of variable names to units, got "
                        f"{type(units).__name__}")
    folder = platform_folder(fmi) if binaries else None
    options = {"input_range": input_range, "input_margin": input_margin, "direction": direction}
    adaptive = {"adapt": adapt, "forgetting": forgetting, "adapt_bound": adapt_bound,
                "dead_zone": dead_zone, "excitation": excitation, "nlms_step": nlms_step,
                "initial_covariance": initial_covariance}
    given = {k: v for k, v in adaptive.items() if v != ADAPT_DEFAULTS[k]}
    comp = _build(model, dtype, limits, initial_command, {**options, **given})
    table = variable_table(comp, sample_period, units, adaptive=adapt != "none")
    with tempfile.TemporaryDirectory(prefix="torchhys-fmu-") as tmp:
        h_path, c_path = to_c(model, tmp, prefix=prefix, dtype=dtype, limits=limits,
                              initial_command=initial_command, **options, **adaptive)
        header, source = h_path.read_bytes(), c_path.read_bytes()
    placeholder = "{" + "0" * 8 + "-0000-0000-0000-" + "0" * 12 + "}"
    wrapper = (f"/* {prefix}_fmu.c: the FMI {fmi}.0 co-simulation wrapper of {prefix}_step, "
               f"generated by torchhys {__version__} (torchhys.deploy.fmu): do not edit. */\n"
               + core_source(prefix, table, placeholder)
               + (FMI2 + FMI2_UNSUPPORTED if fmi == 2 else FMI3 + FMI3_UNSUPPORTED))
    # the token: of the C step, the wrapper (its token a placeholder) and the variables
    digest = hashlib.sha256(header + source + wrapper.encode() + repr(
        (fmi, [v.__dict__ for v in table.all], step_size)).encode()).hexdigest()
    token = "{" + str(uuid.uuid5(_TOKEN_NAMESPACE, digest)) + "}"
    wrapper = wrapper.replace(placeholder, token)
    sources = {f"{prefix}.h": header, f"{prefix}.c": source,
               f"{prefix}_fmu.c": wrapper.encode()}
    c_files = [n for n in sources if n.endswith(".c")]
    if description is None:
        description = (f"torchhys {__version__} hysteresis compensator: "
                       + "; ".join(_describe(model))
                       + f"; command limits [{float(comp.low):.9g}, {float(comp.high):.9g}]; "
                       f"sample period {sample_period!r} s; {str(dtype)[6:]} C step")
    xml = model_description(fmi, prefix=prefix, model_name=model_name or prefix, token=token,
                            description=description, tool=f"torchhys {__version__}",
                            variables=table, step_size=step_size, sources=c_files)
    entries = {"modelDescription.xml": xml.encode()}
    entries.update({f"sources/{n}": data for n, data in sources.items()})
    if fmi == 3:
        entries["sources/buildDescription.xml"] = build_description(prefix, c_files).encode()
    if folder is not None:
        entries[f"binaries/{folder[0]}/{prefix}{folder[1]}"] = _compile(sources, prefix,
                                                                       folder[1])
    write_outputs([(out, _zip(entries))])
    return out


def check_fmu(path: str | os.PathLike) -> dict:
    """Read an FMU back: ``{"fmi": 2 or 3, "model_identifier", "token", "entries"}``, after
    FMPy's validation where FMPy is installed (``torchhys[fmu]``). A file that is not a whole
    zip archive, or an FMU whose model description FMPy finds problems in: ValueError, one
    line."""
    where = os.fspath(path)
    try:
        with zipfile.ZipFile(where) as zf:
            bad = zf.testzip()
            names = zf.namelist()
            xml = zf.read("modelDescription.xml").decode()
    except (zipfile.BadZipFile, KeyError, OSError, EOFError, UnicodeDecodeError) as err:
        raise ValueError(f"{where}: not a readable FMU (a zip archive with "
                         f"modelDescription.xml): {str(err).splitlines()[0]}") from None
    if bad is not None:
        raise ValueError(f"{where}: not a readable FMU: the archive's entry {bad} is damaged")
    try:
        from fmpy.validation import validate_fmu
    except ImportError:
        problems: list[str] = []
    else:
        problems = validate_fmu(where)
    if problems:
        raise ValueError(f"{where}: the FMU's model description has {len(problems)} "
                         f"problem(s): {problems[0].splitlines()[0]}")
    import xml.etree.ElementTree as ET

    root = ET.fromstring(xml)
    cs = root.find("CoSimulation")
    return {"fmi": 2 if root.get("fmiVersion") == "2.0" else 3,
            "model_identifier": None if cs is None else cs.get("modelIdentifier"),
            "token": root.get("guid") or root.get("instantiationToken"), "entries": names}
