"""A compensator fitted from arrays in one call: :class:`Compensator`.

For a notebook user who has a record as arrays (numpy or torch)::

    comp = torchhys.Compensator.fit(response, command, config="measured", verbose=True)
    u = comp.predict(desired)              # the command for a desired response
    comp.score(response_test, command_test)  # RMSE, max error, % of range, baselines
    comp.plot()                            # the fitted loop and the error over time
    comp.export("c", "out/")               # or "torchscript", "onnx", "fmu", "casadi"

:meth:`Compensator.fit` runs the model selection of ``torchhys fit --config NAME``: the
config's candidates (``model.select``), its cross-validation (``select_cv``,
``select_cv_mode``), its rule (``select_rule``), its seed and its training steps, through
:func:`torchhys.selection.select`, the function the command line calls; the chosen
candidate is fitted on the whole record given. The command line also holds out a validation
and a test split of its file: here the caller holds out what it scores (:meth:`score`).
Reading a config needs PyYAML (the ``train`` extra).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchhys.selection.candidates import model_base
from torchhys.selection.run import Selection, select
from torchhys.selection.scores import CandidateScore

__all__ = ["Compensator"]

#: the export formats of :meth:`Compensator.export` and their files
FORMATS = {"c": None, "torchscript": ".pt", "onnx": ".onnx", "fmu": ".fmu", "casadi": ".casadi"}
_SELECT_KEYS = ("select", "select_cv", "select_cv_mode", "select_rule", "select_jobs",
                "select_budget_s")


def _config(config: str | os.PathLike | dict) -> tuple[dict, str]:
    """The config as a dict and its name: a dict as it is, a path that exists, or the name
    of a shipped config (``torchhys configs``)."""
    if isinstance(config, dict):
        return config, "the config dict"
    if not isinstance(config, (str, os.PathLike)):
        raise TypeError(f"config must be a shipped config's name, a path or a dict, got "
                        f"{type(config).__name__}")
    path = Path(config)
    if not path.is_file():
        from torchhys.cli.configs import shipped_configs

        shipped = shipped_configs()
        name = path.stem if path.suffix == ".yaml" else str(config)
        if name not in shipped:
            raise ValueError(f"config {os.fspath(config)!r}: no such file, and no shipped "
                             f"config of that name (shipped: {', '.join(shipped)})")
        path = shipped[name]
    try:
        import yaml
    except ImportError:
        raise ImportError('reading a config needs PyYAML: pip install "torchhys[train]" '
                          '(or give config as a dict)') from None
    with path.open(encoding="utf-8") as fh:
        loaded = yaml.safe_load(fh)
    if not isinstance(loaded, dict) or not isinstance(loaded.get("model"), dict):
        raise ValueError(f"config {path}: expected a mapping with a model section")
    return loaded, str(path)


def _rows(value: Any, name: str) -> list[np.ndarray]:
    """An array (time,), (rows, time) or a list of 1-d arrays as float64 rows."""
    if isinstance(value, (list, tuple)) and value and not np.isscalar(value[0]):
        rows = [_rows(v, f"{name}[{i}]")[0] for i, v in enumerate(value)]
        return rows
    if isinstance(value, Tensor):
        value = value.detach().cpu().numpy()
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be an array of numbers (numpy, torch or a list), got "
                        f"{type(value).__name__}") from None
    if arr.ndim not in (1, 2) or arr.size == 0:
        raise ValueError(f"{name} must be (time,) or (rows, time) and not empty, got shape "
                         f"{arr.shape}")
    return [arr] if arr.ndim == 1 else list(arr)


def _record(response: Any, command: Any, recordings: Any) -> tuple[Tensor, Tensor, Tensor]:
    """``(x, y, mask)`` (rows, time) float64 and bool: rows padded to the longest."""
    xs, ys = _rows(response, "response"), _rows(command, "command")
    if recordings is not None:
        if len(xs) != 1 or len(ys) != 1:
            raise ValueError("recordings labels each sample of a 1-d response and command; "
                             "with rows (or a list), leave recordings out")
        labels = np.asarray(recordings)
        if labels.shape != xs[0].shape:
            raise ValueError(f"recordings must label each sample: shape {xs[0].shape}, got "
                             f"{labels.shape}")
        cuts = np.flatnonzero(labels[1:] != labels[:-1]) + 1
        xs, ys = np.split(xs[0], cuts), np.split(ys[0], cuts)
    if len(xs) != len(ys) or any(a.shape != b.shape for a, b in zip(xs, ys, strict=True)):
        raise ValueError(f"response and command must have the same shape, got "
                         f"{[a.shape for a in xs]} and {[b.shape for b in ys]}")
    n = max(len(a) for a in xs)
    x = torch.zeros(len(xs), n, dtype=torch.float64)
    y = torch.zeros_like(x)
    mask = torch.zeros(len(xs), n, dtype=torch.bool)
    for r, (a, b) in enumerate(zip(xs, ys, strict=True)):
        x[r, :len(a)], y[r, :len(b)], mask[r, :len(a)] = torch.from_numpy(a), \
            torch.from_numpy(b), True
        x[r, len(a):], y[r, len(b):] = x[r, len(a) - 1], y[r, len(b) - 1]  # held padding
    return x, y, mask


class _Reporter:
    """:class:`torchhys.selection.run.Progress` for :meth:`Compensator.fit`: ``verbose``
    prints a line per scored candidate; ``callback(done, total, score)`` is told too."""

    def __init__(self, total: int, verbose: bool,
                 callback: Callable[[int, int, CandidateScore], None] | None) -> None:
        self.total, self.verbose, self.callback, self.done = total, verbose, callback, 0

    def starts(self, candidate: int, fold: int | None) -> None:
        if self.verbose and fold in (None, 0):
            print(f"candidate {candidate} ({candidate + 1} of {self.total}) starts",
                  file=sys.stderr, flush=True)

    def scored(self, score: CandidateScore) -> None:
        self.done += 1
        if self.verbose:
            print(f"candidate {score.index}: validation MSE {score.val_mse:.4g} "
                  f"({self.done} of {self.total})", file=sys.stderr, flush=True)
        if self.callback is not None:
            self.callback(self.done, self.total, score)


class Compensator:
    """A fitted inverse model (response -> command) with its selection and training
    record; build it with :meth:`fit`.

    Attributes:
        model: the chosen candidate fitted on the whole record
            (:class:`~torchhys.InverseHysteresisNet`).
        selection: what :func:`torchhys.selection.select` found (every candidate's score,
            the choice, :meth:`~torchhys.selection.run.Selection.table`).
        limits: the training commands' range (the exported command's saturation).
    """

    def __init__(self, selection: Selection, x: Tensor, y: Tensor, mask: Tensor,
                 warmup: int = 0) -> None:
        self.selection = selection
        self.model = selection.fit()
        self._x, self._y, self._mask = x, y, mask
        self._scored = mask.clone()  # the baselines' samples: the scored ones
        self._scored[:, :warmup] = False
        self.limits = (float(y[mask].min()), float(y[mask].max()))

    @classmethod
    def fit(cls, response: Any, command: Any, *, config: str | os.PathLike | dict = "measured",
            recordings: Any = None, warmup: int | None = None, jobs: int | str = 1,
            verbose: bool = False,
            progress: Callable[[int, int, CandidateScore], None] | None = None,
            ) -> Compensator:
        """Choose and fit a compensator of the record ``(response, command)`` as ``torchhys
        fit --config NAME`` chooses it (the module docstring).

        Args:
            response, command: the device's measured response and the command that produced
                it: (time,), (rows, time) or a list of 1-d arrays (recordings of different
                lengths), numpy or torch. The compensator maps a desired response to a
                command.
            config: a shipped config's name (``"measured"``, ``"compensator"``: ``torchhys
                configs``), a YAML path, or the config as a dict.
            recordings: a label per sample of 1-d arrays (a run column): each run of equal
                labels is a recording (a row).
            warmup: samples of each recording left out of the scores (default: the
                config's ``data.warmup``, else 0).
            jobs: candidates scored at a time (``"auto"``: as ``model.select_jobs``).
            verbose: print a line as each candidate starts and is scored, and the table.
            progress: called as ``progress(done, total, score)`` after each candidate.

        Raises:
            ValueError, TypeError: bad arrays or config, naming the argument.
        """
        cfg, source = _config(config)
        model = dict(cfg["model"])
        candidates = model.get("select") or [{}]
        if not isinstance(candidates, list):
            raise ValueError(f"{source}: model.select must be a list of candidates")
        data = cfg.get("data") or {}
        trainer = cfg.get("trainer") or {}
        if warmup is None:
            warmup = int(data.get("warmup") or 0)
        x, y, mask = _record(response, command, recordings)
        reporter = _Reporter(len(candidates), verbose, progress)
        seed = cfg.get("seed_everything")
        selection = select(
            candidates, x, y, base=model_base(model), warmup=warmup, mask=mask,
            cv=model.get("select_cv", 4), mode=model.get("select_cv_mode"),
            rule=model.get("select_rule") or "min", jobs=jobs,
            budget_s=model.get("select_budget_s"),
            seed=seed if isinstance(seed, int) and not isinstance(seed, bool) else 0,
            epochs=int(trainer.get("max_epochs") or 10), progress=reporter,
            source="the arrays")
        comp = cls(selection, x, y, mask, warmup)
        if verbose:
            print(selection.table(), file=sys.stderr, flush=True)
        return comp

    def predict(self, desired: Any) -> np.ndarray:
        """The command for the desired response ``desired`` ((time,) or (rows, time)), from
        a fresh state, float64 numpy."""
        rows = _rows(desired, "desired")
        x = torch.from_numpy(np.stack(rows)) if len({len(r) for r in rows}) == 1 else None
        if x is None:
            return np.array([self.predict(r) for r in rows], dtype=object)
        with torch.no_grad():
            u, _ = self.model(x)
        u = u.numpy()
        return u[0] if np.ndim(desired) == 1 or isinstance(desired, Tensor) and \
            desired.dim() == 1 else u

    def score(self, response: Any, command: Any) -> dict[str, float]:
        """The compensator's error on a record (held out, for an honest score): the RMSE,
        the largest error, the RMSE in % of the command's range, and the ratio of the RMSE
        to the better of a straight line and a memoryless polynomial fitted on the training
        record's scored samples (below 1: the hysteresis model earns its place)."""
        from torchhys.training.baselines import fit_polynomial

        x, y, mask = _record(response, command, None)
        with torch.no_grad():
            u, _ = self.model(x)
        err = (u - y)[mask]
        rmse = float(err.square().mean().sqrt())
        span = float(y[mask].max() - y[mask].min())
        baselines = {}
        for name, degrees in (("line", (1,)), ("polynomial", range(1, 10))):
            p = fit_polynomial(self._x, self._y, self._scored, degrees=degrees)
            baselines[name] = float((p(x) - y)[mask].square().mean().sqrt())
        best = min(baselines.values())
        return {"rmse": rmse, "max_error": float(err.abs().max()),
                "rmse_pct_of_range": 100.0 * rmse / span if span > 0 else float("nan"),
                "line_rmse": baselines["line"], "polynomial_rmse": baselines["polynomial"],
                "ratio_to_baseline": rmse / best if best > 0 else float("inf")}

    def plot(self, response: Any = None, command: Any = None, path: str | os.PathLike | None
             = None) -> Any:
        """A figure of the fitted loop (command against response, the record and the
        model) and the error over time, on the training record or on ``(response,
        command)``; written to ``path`` where given. Returns the matplotlib figure."""
        import matplotlib

        if path is not None:
            matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        if response is None:
            x, y, mask = self._x, self._y, self._mask
        else:
            x, y, mask = _record(response, command, None)
        with torch.no_grad():
            u, _ = self.model(x)
        fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
        for r in range(x.shape[0]):
            m = mask[r].numpy()
            a.plot(x[r].numpy()[m], y[r].numpy()[m], color="0.6", lw=1,
                   label="record" if r == 0 else None)
            a.plot(x[r].numpy()[m], u[r].numpy()[m], color="C0", lw=1,
                   label="model" if r == 0 else None)
            b.plot((u[r] - y[r]).numpy()[m], lw=0.8)
        a.set(xlabel="response", ylabel="command", title=f"chosen: candidate "
              f"{self.selection.chosen.index}")
        a.legend()
        b.set(xlabel="sample", ylabel="command error", title="error over time")
        fig.tight_layout()
        if path is not None:
            fig.savefig(path, dpi=100)
        return fig

    def export(self, format: str, out: str | os.PathLike, **options: Any) -> Any:
        """Write the compensator as ``format`` (``"c"``: ``out`` an existing folder;
        ``"torchscript"``, ``"onnx"``, ``"fmu"``, ``"casadi"``: a file) with the command
        saturated to the training commands' range unless ``limits`` is given; ``options``
        go to the exporter (:mod:`torchhys.deploy`)."""
        if format not in FORMATS:
            raise ValueError(f"format must be one of {sorted(FORMATS)}, got {format!r}")
        options.setdefault("limits", self.limits)
        if format == "c":
            from torchhys.deploy.c import to_c
            return to_c(self.model, out, **options)
        if format == "fmu":
            from torchhys.deploy.export_fmu import to_fmu
            return to_fmu(self.model, out, **options)
        if format == "casadi":
            from torchhys.deploy.export_casadi import save_casadi, to_casadi
            return save_casadi(to_casadi(self.model, **options), out)
        from torchhys.deploy.export import _compensator
        comp = _compensator(self.model, options.pop("limits"), options.pop(
            "initial_command", 0.0), options)
        if format == "onnx":
            from torchhys.deploy.export_onnx import to_onnx
            return to_onnx(comp, out)
        from torchhys.deploy.export import to_torchscript
        return to_torchscript(comp, out)

    def __repr__(self) -> str:
        spec = self.selection.spec.get("operator")
        return (f"Compensator(chosen candidate {self.selection.chosen.index}: operator="
                f"{spec!r}, limits={self.limits})")
