"""Export a fleet: the compensators of many devices, one file per device, or one C step
shared by all of them with a table of each device's constants.

:func:`read_fleet` reads the devices of a ``torchhys fleet`` folder (``fleet.csv`` and each
identified device's ``logs/version_0/checkpoints/last.ckpt``); :func:`export_fleet` writes
the models of a fleet (name -> model) in one format:

==================  =========================================================================
``format``          files in ``out_dir``
==================  =========================================================================
``"c"``, shared     ``PREFIX.h``, ``PREFIX.c`` (``PREFIX_step(PREFIX_state *s, const
                    PREFIX_params *p, PREFIX_real x)``, written once) and ``PREFIX_params.c``
                    (``PREFIX_params_table[PREFIX_N_DEVICES]``, ``PREFIX_device_names``)
``"c"``             ``PREFIX_<device>.h`` and ``.c`` a device (:func:`torchhys.deploy.c.to_c`)
``"onnx"``          ``<device>.onnx`` (:func:`torchhys.deploy.export_onnx.to_onnx`)
``"torchscript"``   ``<device>.pt`` (:func:`torchhys.deploy.export.to_torchscript`)
``"fmu"``           ``<device>.fmu``, model identifier ``PREFIX_<device>``
                    (:func:`torchhys.deploy.export_fmu.to_fmu`)
==================  =========================================================================

(``<device>`` in a C name: :func:`~torchhys.deploy.c._shared.c_identifier`, characters
other than letters, digits and ``_`` as ``_``.) The devices share a step when the step the
C generator writes for each is the same text once every constant tensor is read from
``p``: the same operators, sizes and literals. Every constant tensor may differ between
the devices (weights, the input normalisation, the command's saturation, the input
clamp's bounds, the direction guard): those that differ are the fields of
``PREFIX_params``, those equal in every device are written once into the step. Python
numbers the traced step bakes into its code, and code the generator chose from a
constant's values, must be equal; where they are not, or the devices chose other
structures, ``shared=None`` writes one pair of files per device and says why
(:attr:`FleetExport.reason`); ``shared=True`` raises it.
"""

from __future__ import annotations

import copy
import csv
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchhys.deploy.c import DEFAULT_PREFIX, check_prefix, to_c
from torchhys.deploy.c._shared import NotShared, c_identifier, device_step, shared_files
from torchhys.deploy.export import to_torchscript, write_outputs
from torchhys.deploy.export_fmu import to_fmu
from torchhys.deploy.export_onnx import to_onnx

__all__ = ["CHECKPOINT", "FORMATS", "FleetDevices", "FleetExport", "export_fleet",
           "read_fleet"]

FORMATS = ("c", "onnx", "torchscript", "fmu")
"""The formats of :func:`export_fleet`."""
CHECKPOINT = Path("logs") / "version_0" / "checkpoints" / "last.ckpt"
"""A device's checkpoint in its run folder."""
_SUFFIX = {"onnx": ".onnx", "torchscript": ".pt", "fmu": ".fmu"}


@dataclass(frozen=True)
class FleetDevices:
    """The devices of a fleet folder: ``checkpoints`` (device -> its ``last.ckpt``, in the
    order of ``fleet.csv``) and ``skipped`` (device -> why: failed in the fleet, or no
    checkpoint)."""

    folder: Path
    checkpoints: dict[str, Path]
    skipped: dict[str, str]


@dataclass(frozen=True)
class FleetExport:
    """What :func:`export_fleet` wrote: ``files`` (in order), ``shared`` (one C step for
    every device) and ``reason`` (why the C is one pair a device where sharing was
    possible to ask: ``""`` when shared or not asked)."""

    files: list[Path]
    shared: bool
    devices: list[str]
    reason: str = field(default="")


def _check_name(name: object) -> str:
    if not isinstance(name, str) or name in ("", ".", "..") or "/" in name or os.sep in name:
        raise ValueError(f"device names must be file names (no '/'), got {name!r}")
    return name


def read_fleet(folder: str | os.PathLike, *, what: str = "folder") -> FleetDevices:
    """The devices of the ``torchhys fleet`` folder ``folder`` (``ROOT/fleet_N``).

    A device of status ``ok`` in ``fleet.csv`` is read from ``folder/<device>/``
    (:data:`CHECKPOINT`), the ``run_dir`` of its row where that folder is missing; the
    others are skipped, with the reason of their row.

    Raises:
        ValueError: ``folder`` is no folder, has no ``fleet.csv``, that file lacks the
            ``device`` and ``status`` columns, or no device was identified (each message
            starts with ``what`` and the folder).
    """
    path = Path(folder)
    table = path / "fleet.csv"
    if not path.is_dir():
        raise ValueError(f"{what} {os.fspath(folder)}: no such folder")
    if not table.is_file():
        raise ValueError(f"{what} {os.fspath(folder)}: no fleet.csv (expected the folder "
                         "ROOT/fleet_N of a torchhys fleet)")
    with table.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        rows = list(reader)
        columns = reader.fieldnames or []
    if not {"device", "status"} <= set(columns):
        raise ValueError(f"{what} {os.fspath(folder)}: fleet.csv lacks the columns device and "
                         f"status (it has {list(columns)})")
    found, skipped = {}, {}
    for row in rows:
        name = _check_name(row["device"])
        if row["status"] != "ok":
            skipped[name] = (row.get("reason") or row["status"]).strip()
            continue
        ckpt = path / name / CHECKPOINT
        if not ckpt.is_file() and row.get("run_dir"):
            ckpt = Path(row["run_dir"]) / CHECKPOINT
        if ckpt.is_file():
            found[name] = ckpt
        else:
            skipped[name] = f"no checkpoint {path / name / CHECKPOINT}"
    if not found:
        raise ValueError(f"{what} {os.fspath(folder)}: no device with a checkpoint "
                         f"(fleet.csv: {len(rows)} rows, {len(skipped)} failed or without one)")
    return FleetDevices(path, found, skipped)


def _dtype_of(model: nn.Module) -> torch.dtype:
    for t in (*model.parameters(), *model.buffers()):
        if t.is_floating_point():
            return t.dtype
    return torch.float64


def _in(model: nn.Module, dtype: torch.dtype) -> nn.Module:
    return model if _dtype_of(model) == dtype else copy.deepcopy(model).to(dtype)


def _check_free(paths: list[Path], overwrite: bool) -> None:
    for p in paths:
        if p.is_dir():
            raise ValueError(f"out_dir: {p} is a folder; move it or give another out_dir")
        if p.exists() and not overwrite:
            raise ValueError(f"out_dir: {p} exists; pass overwrite=True (--force) to replace "
                             "it, or give another out_dir")


def export_fleet(
    models: Mapping[str, nn.Module], out_dir: str | os.PathLike, *, format: str = "c",
    prefix: str = DEFAULT_PREFIX, shared: bool | None = None, dtype: torch.dtype | None = None,
    overwrite: bool = True, limits: tuple[float, float] | None = None,
    initial_command: float = 0.0, input_range: tuple[float, float] | None = None,
    input_margin: float | None = 0.05, direction: str = "auto", fmi: int = 2,
    step_size: float | None = None, sample_period: float | None = None,
) -> FleetExport:
    """Export the compensators of a fleet's ``models`` (device name -> model) into
    ``out_dir`` (the module docstring).

    Args:
        models: the devices' models (each as :func:`torchhys.deploy.c.to_c` takes it), in
            the order of the C tables.
        out_dir: an existing folder.
        format: one of :data:`FORMATS`.
        prefix: the C prefix (``"c"``; ``"fmu"``: of the model identifiers).
        shared: ``"c"`` only: None (one shared step where the devices allow it, else one
            pair of files a device and :attr:`FleetExport.reason`), True (shared, or
            ValueError with the difference) or False (one pair a device).
        dtype: the real type (default: each model's own; a shared step needs one).
        overwrite: replace existing files (else ValueError naming the first, before
            anything is written).
        limits, initial_command, input_range, input_margin, direction: as
            :func:`torchhys.deploy.c.to_c`, the same for every device.
        fmi, step_size, sample_period: ``"fmu"``: as :func:`torchhys.deploy.export_fmu.to_fmu`.

    Returns:
        A :class:`FleetExport`.

    Raises:
        ValueError: an unknown ``format``, ``shared`` with another format than ``"c"``,
            ``shared=True`` where the steps differ, no models, a bad device name, a bad
            ``prefix`` or ``out_dir``, an existing file without ``overwrite``; the
            per-format exporters' errors.
    """
    if format not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {format!r}")
    if shared is not None and format != "c":
        raise ValueError(f"shared applies to format 'c' only, not {format!r}")
    if not models:
        raise ValueError("models: no device")
    prefix, folder = check_prefix(prefix), Path(out_dir)
    if not folder.is_dir():
        raise ValueError(f"out_dir {os.fspath(out_dir)!r} is not an existing folder")
    names = [_check_name(n) for n in models]
    ids = {n: c_identifier(n) for n in names}
    if len(set(ids.values())) < len(ids):
        raise ValueError(f"devices of one C name ({sorted(ids.values())}): rename them")
    options = {"limits": limits, "initial_command": initial_command,
               "input_range": input_range, "input_margin": input_margin,
               "direction": direction}
    dtypes = {n: dtype or _dtype_of(m) for n, m in models.items()}
    reason = ""
    if format == "c" and shared is not False:
        try:
            if len(set(dtypes.values())) > 1:
                raise NotShared("the devices' models are of several dtypes: "
                                f"{sorted({str(d) for d in dtypes.values()})} (give dtype)")
            steps = {n: device_step(models[n], prefix, dtypes[n], options) for n in names}
            texts = shared_files(prefix, steps)
        except NotShared as err:
            if shared:
                raise ValueError(f"shared: {err}") from None
            reason = str(err)
        else:
            paths = [folder / f"{prefix}.h", folder / f"{prefix}.c",
                     folder / f"{prefix}_params.c"]
            _check_free(paths, overwrite)
            write_outputs([(p, t.encode()) for p, t in zip(paths, texts, strict=True)])
            return FleetExport(paths, True, names)
    return FleetExport(_per_device(models, folder, format, prefix, ids, dtypes, overwrite,
                                   options, {"fmi": fmi, "step_size": step_size,
                                             "sample_period": sample_period}),
                       False, names, reason)


def _per_device(models: Mapping[str, nn.Module], folder: Path, format: str, prefix: str,
                ids: dict[str, str], dtypes: dict[str, torch.dtype], overwrite: bool,
                options: dict[str, Any], fmu: dict[str, Any]) -> list[Path]:
    """One file (C: a pair) a device."""
    def targets(name: str) -> list[Path]:
        if format == "c":
            return [folder / f"{prefix}_{ids[name]}.h", folder / f"{prefix}_{ids[name]}.c"]
        return [folder / f"{name}{_SUFFIX[format]}"]

    _check_free([p for n in models for p in targets(n)], overwrite)
    written: list[Path] = []
    for name, model in models.items():
        dtype, path = dtypes[name], targets(name)
        if format == "c":
            to_c(model, folder, prefix=f"{prefix}_{ids[name]}", dtype=dtype, **options)
        elif format == "fmu":
            to_fmu(model, path[0], prefix=f"{prefix}_{ids[name]}", dtype=dtype, **fmu,
                   **options)
        elif format == "onnx":
            to_onnx(_in(model, dtype), path[0], **options)
        else:
            to_torchscript(_in(model, dtype), path[0], **options)
        written += path
    return written
