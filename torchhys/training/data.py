"""``HysteresisDataModule``: a simulated plant, or recorded (command, response) files, as
Lightning's data.

Each stage (train, val, test) is one full batch of the stage's sequences, one row per
recording (``predict``: one batch per recording, unpadded): ``(x, y, warmup, mask)``, laid
out as :mod:`torchhys.data.tensors` draws it; the loss and the metrics cover the masked
samples only. The reading, the splits and the tensors are :mod:`torchhys.data`'s (no
Lightning); this module holds the Lightning face over them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import lightning as L
import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from torchhys._checks import check_choice, check_int
from torchhys._finite import check_scale
from torchhys._memory import check_repeat
from torchhys.data.files import (
    Recording,
    check_condition_columns,
    read_recordings,
    resolve_path,
)
from torchhys.data.simulations import SIMULATIONS, simulate
from torchhys.data.splits import STAGES, Window, assign_recordings, check_split
from torchhys.data.tables import Column, DataFileError, RecordingId, check_text_options
from torchhys.data.tensors import (
    FitTensors,
    StageBatch,
    pad_rows,
    stack_sequences,
    stage_batch,
    window_conditions,
    window_sequence,
)

__all__ = ["SPLIT_BY", "HysteresisDataModule", "SequenceDataset"]

SPLIT_BY = ("time", "recording")
"""``time``: each recording split in time order; ``recording``: whole recordings per stage."""


class SequenceDataset(Dataset):
    """One sequence ``(x, y, warmup)``: ``x``, ``y`` of shape (time,) and the number of
    leading warm-up samples (the preceding part of the record) excluded from metrics."""

    def __init__(self, x: Tensor, y: Tensor, warmup: int = 0) -> None:
        self.x, self.y, self.warmup = x, y, torch.tensor(warmup)

    def __len__(self) -> int:
        return 1

    def __getitem__(self, index: int) -> tuple[Tensor, Tensor, Tensor]:
        return self.x, self.y, self.warmup


class _Batches(Dataset):
    """Ready batches, one per item (loaded with ``batch_size=1`` and :func:`_only`)."""

    def __init__(self, batches: list[StageBatch]) -> None:
        self.batches = batches

    def __len__(self) -> int:
        return len(self.batches)

    def __getitem__(self, index: int) -> StageBatch:
        return self.batches[index]


def _only(items: list[StageBatch]) -> StageBatch:
    """Collate a batch of one ready batch: the batch itself."""
    return items[0]


class HysteresisDataModule(L.LightningDataModule):
    """Full-sequence data for inverse-hysteresis training.

    The source is a simulated plant (``simulation``, by default the paper's Section 5.2:
    input ``h = H[x]``, target ``x``) unless ``path`` names recorded CSV or NPZ files. A
    file is one recording, or ``run_column`` splits it into several (consecutive rows with
    one id). Each recording runs from a fresh operator state with its own warm-up, and
    each stage is one full batch (layout in the module docstring).

    Splits (``split_by``): ``"time"`` cuts each recording in time order, and the validation
    and test sequences carry the preceding record as warm-up (so operator states continue
    as in deployment; metrics cover the split's own samples only); ``"recording"`` gives
    whole recordings to the stages (see :func:`assign_recordings`).

    Args:
        path: a recorded ``.csv``/``.npz`` file, a list of them with the same columns (see
            :func:`torchhys.data.files.read_recordings`), or None for a simulation.
        input_column: column of the model input (the plant's response), name or index.
        target_column: column of the model target (the command), name or index.
        time_column: optional column of sample times (checked to increase per recording).
        run_column: optional column of recording ids (name or index) splitting a file into
            recordings; the ids name them in ``*_recordings`` (without it, a file's index
            in ``path`` is its id).
        simulation: ``"paper"``, ``"fig6"`` or ``"bouc_wen"`` when ``path`` is None.
        dt: sampling step of the simulation.
        t_end: end time of the simulation.
        seed: seed of the simulation's random signal (``"bouc_wen"``).
        split: ``"paper"`` (all data for train, validation and test, as the paper reports
            training MSE) or fractions ``[train, val, test]`` (sum <= 1) of each recording's
            samples (``split_by="time"``) or of the recordings in order (``"recording"``).
        split_by: ``"time"`` or ``"recording"``.
        train_recordings: ids of the training recordings (``split_by="recording"``).
        val_recordings: ids of the validation recordings (``[]``: no validation).
        test_recordings: ids of the test recordings (``[]``: no test).
        repeat: periods each recording runs back to back, int >= 1: a closed steady-state
            loop runs ``repeat`` times from a fresh state and only the last period is
            scored (the first ``repeat - 1`` are warm-up).
        min_samples: fewest rows of a recording, and of each non-empty part of a recording
            split in time.
        warmup: leading samples of each recording's sequence left out of the training loss
            and of the fits of data-dependent operators (with ``split="paper"`` or
            ``split_by="recording"`` also of the metrics): the model's operators start from
            a zero state, a recorded plant from its own, so the first samples after the
            start disagree (states still run through them).
        encoding: the text encoding of CSV files (``"latin-1"``, ``"cp1252"``, ...); None:
            UTF-8, with or without a byte-order mark.
        delimiter: the character between the fields of CSV files (``","``, ``";"``, a tab,
            also ``"tab"``); None: sniffed among ``,``, ``;`` and tab.
        decimal: the decimal mark of numbers in CSV files, ``"."`` or ``","`` (the
            delimiter is then ``;`` or a tab). The three are those of
            :func:`torchhys.data.files.read_recordings`; NPZ files ignore them.
        condition_columns: columns of measured operating conditions (a coil voltage, a
            supply pressure, a temperature; constant within a recording or varying sample
            by sample): each stage's batch then carries them as its fifth member, (rows,
            time, n) (:mod:`torchhys.data.tensors`), and a network with ``n_conditions``
            takes them.

    Raises:
        ValueError: a bad split, ``split_by``, ``repeat``, ``warmup``, ``encoding``,
            ``delimiter`` or ``decimal`` (named ``data.<option>``); recording lists with
            ``split_by="time"``; ``run_column`` without ``path``; at :meth:`setup`, an
            empty split, an unknown recording id, too few samples in a split.
        torchhys.data.tables.DataFileError: problems in a file (names file, column and
            row or recording), a recording not longer than its warm-up; at
            :meth:`train_tensors`, a constant input or target column over the training
            split (names the files and the column option).
    """

    def __init__(
        self, *, path: str | list[str] | None = None, input_column: Column = "response",
        target_column: Column = "command", time_column: Column | None = None,
        run_column: Column | None = None, simulation: str = "paper", dt: float = 0.01,
        t_end: float = 8 * math.pi, seed: int = 0, split: str | list[float] = "paper",
        split_by: str = "time", train_recordings: list[RecordingId] | None = None,
        val_recordings: list[RecordingId] | None = None,
        test_recordings: list[RecordingId] | None = None, repeat: int = 1,
        min_samples: int = 16, warmup: int = 0, encoding: str | None = None,
        delimiter: str | None = None, decimal: str = ".",
        condition_columns: list[Column] | None = None,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        self._check_inputs()
        self.fractions = check_split(split)
        self.recordings: list[Recording] = []
        self.windows: dict[str, list[Window]] = {}
        self.t: Tensor | None = None
        self.x: Tensor | None = None
        self.y: Tensor | None = None
        self.bounds: dict[str, tuple[int, int]] = {}
        """Rows ``[a, b)`` of each stage of a single recording split in time."""
        self._fit: FitTensors | None = None  # the training rows, padded once (_train_fit)

    def _check_inputs(self) -> None:
        hp = self.hparams
        check_int(hp.warmup, "warmup", minimum=0)
        check_int(hp.min_samples, "min_samples", minimum=1)
        check_int(hp.repeat, "repeat", minimum=1)
        check_choice(hp.split_by, "split_by", SPLIT_BY)
        check_text_options(hp.encoding, hp.delimiter, hp.decimal, prefix="data.")
        check_condition_columns(hp.condition_columns, hp.input_column, hp.target_column,
                                hp.time_column, hp.run_column)
        if hp.path is None and hp.condition_columns:
            raise ValueError(f"condition_columns={list(hp.condition_columns)!r} needs recorded "
                             "data: set path to the file(s)")
        if hp.path is None:
            check_choice(hp.simulation, "simulation", SIMULATIONS)
            if hp.run_column is not None:
                raise ValueError(
                    f"run_column={hp.run_column!r} needs recorded data: set path to the file(s)"
                )
        elif not isinstance(hp.path, (str, Path)) and not (
            isinstance(hp.path, Sequence) and hp.path
            and all(isinstance(p, (str, Path)) for p in hp.path)
        ):
            raise ValueError(f"path must be a file or a non-empty list of files, got {hp.path!r}")
        if hp.path is not None and not isinstance(hp.path, (str, Path)):
            seen: set[Path] = set()
            for p in hp.path:
                resolved = resolve_path(p)
                if resolved in seen:
                    raise ValueError(f"path lists the file {str(p)!r} twice: each recording "
                                     "once, or its copies would be in training and held out")
                seen.add(resolved)
        listed = [f"{s}_recordings" for s in STAGES if hp[f"{s}_recordings"] is not None]
        if listed and hp.split_by != "recording":
            raise ValueError(
                f"{', '.join(listed)} need split_by='recording', got split_by={hp.split_by!r}"
            )

    # -----------------------------------------------------------------------------------
    def _load(self) -> None:
        hp = self.hparams
        if hp.path is None:
            t, x, y = simulate(hp.simulation, dt=hp.dt, t_end=hp.t_end, seed=hp.seed)
            self.recordings = [Recording(0, f"simulation {hp.simulation!r}", x.numpy(),
                                         y.numpy(), t.numpy())]
        else:
            self.recordings = read_recordings(
                hp.path, input_column=hp.input_column, target_column=hp.target_column,
                time_column=hp.time_column, run_column=hp.run_column,
                min_samples=hp.min_samples, encoding=hp.encoding, delimiter=hp.delimiter,
                decimal=hp.decimal, condition_columns=hp.condition_columns)
        recs = self.recordings
        check_repeat(hp.repeat, sum(len(r.x) for r in recs))  # memory, before it is taken
        self.x = torch.from_numpy(np.concatenate([r.x for r in recs]))
        self.y = torch.from_numpy(np.concatenate([r.y for r in recs]))
        self.t = (None if any(r.t is None for r in recs)
                  else torch.from_numpy(np.concatenate([r.t for r in recs])))
        if hp.split_by == "time":
            self.windows = self._time_windows()
        else:
            lists = {s: hp[f"{s}_recordings"] for s in STAGES}
            chosen = assign_recordings([r.id for r in recs], hp.split, lists, where=self.source)
            self.windows = {s: [Window(i, 0, len(recs[i].x)) for i in chosen[s]]
                            for s in STAGES}
        self._check_warmup()

    def _time_windows(self) -> dict[str, list[Window]]:
        hp = self.hparams
        windows: dict[str, list[Window]] = {s: [] for s in STAGES}
        for i, rec in enumerate(self.recordings):
            n = len(rec.x)
            if hp.split == "paper":
                bounds = {s: (0, n) for s in STAGES}
            else:
                ends = [round(n * sum(self.fractions[: k + 1])) for k in range(3)]
                bounds = dict(zip(STAGES, zip([0, ends[0], ends[1]], ends, strict=True),
                                  strict=True))
            for stage, (a, b) in bounds.items():
                if 0 < b - a < hp.min_samples or (stage == "train" and b - a < hp.min_samples):
                    err = DataFileError if hp.path is not None else ValueError
                    raise err(
                        f"{rec.label}: the {stage} split holds {b - a} samples (rows "
                        f"{a}..{b - 1} of {n}), at least {hp.min_samples} are needed; record "
                        "more data or change "
                        f"split={list(self.fractions) if hp.split != 'paper' else 'paper'}"
                    )
                if b > a:
                    windows[stage].append(Window(i, a, b))
            if len(self.recordings) == 1:
                self.bounds = bounds
        return windows

    def _check_warmup(self) -> None:
        hp = self.hparams
        for stage, windows in self.windows.items():
            for w in windows:
                rec = self.recordings[w.index]
                x, _, first = self._sequence(w)
                scored = x.numel() - first
                if hp.split_by == "time" and stage == "train" and scored < hp.min_samples:
                    raise ValueError(
                        f"{rec.label}: warmup={hp.warmup} leaves {max(scored, 0)} of the "
                        f"{w.end - w.start} training samples, at least {hp.min_samples} are "
                        "needed; lower warmup"
                    )
                if scored <= 0:
                    n = len(rec.x)
                    k = f" (repeat={hp.repeat}: {hp.repeat * n})" if hp.repeat > 1 else ""
                    raise DataFileError(
                        f"{rec.label} holds {n} samples{k}, not more than warmup="
                        f"{hp.warmup}; lower warmup, or leave the recording out of {stage}"
                    )

    def _check_varies(self) -> None:
        """The input and the target must vary over the training split: the normalization
        fitted on :meth:`train_tensors` divides by their standard deviations."""
        hp = self.hparams
        windows = self._stage_windows("train")
        if not windows:
            return
        recs = [self.recordings[w.index] for w in windows]
        where = (recs[0].label if len(recs) == 1
                 else f"{self.source} (training recordings {[r.id for r in recs]})")
        for option, role in (("input_column", "x"), ("target_column", "y")):
            values = np.concatenate([getattr(self.recordings[w.index], role)[: w.end]
                                     for w in windows])
            err, what = ((ValueError, f"the simulated {option.split('_')[0]}") if hp.path is None
                         else (DataFileError, f"data.{option} {hp[option]!r}"))
            check_scale(values, f"{where}: {what}", err)  # a finite mean and spread
            if not np.std(values) > 0:  # equal, or too close for float64 (subnormal)
                lo, hi = float(values.min()), float(values.max())
                spread = f"all {lo:.10g}" if lo == hi else f"{lo:.3g} to {hi:.3g}, std 0"
                raise err(
                    f"{where}: {what} is constant over the training split ({values.size} "
                    f"samples, {spread}); the normalization needs a "
                    "varying input and target: check the column (is it the right one?) and "
                    "the split")
        for k, column in enumerate(hp.condition_columns or ()):
            values = np.concatenate([self.recordings[w.index].conditions[: w.end, k]
                                     for w in windows])
            if not np.std(values) > 0:
                raise DataFileError(
                    f"{where}: data.condition_columns[{k}] {column!r} is constant over the "
                    f"training split (all {float(values[0]):.10g}): a condition that does not "
                    "vary cannot schedule a model; train on several conditions, or drop it")

    @property
    def n_conditions(self) -> int:
        """Operating conditions per sample (``condition_columns``; 0: none)."""
        return len(self.hparams.condition_columns or ())

    def prepare_data(self) -> None:
        """Nothing to download: data are simulated or read in :meth:`setup`."""

    def setup(self, stage: str | None = None) -> None:
        """Read (or simulate) the data and split it, once."""
        if self.x is None:
            self._load()

    # -----------------------------------------------------------------------------------
    def _sequence(self, w: Window) -> tuple[Tensor, Tensor, int]:
        """``(x, y, first)`` of a window: (time,) tensors, ``repeat - 1`` whole periods then
        rows ``[0, end)``, and the index of the first scored sample."""
        return window_sequence(self.recordings[w.index], w, repeat=int(self.hparams.repeat),
                               warmup=int(self.hparams.warmup))

    def _conditions(self, w: Window) -> Tensor | None:
        """The conditions (time, n) of a window's sequence (None: no condition columns)."""
        return window_conditions(self.recordings[w.index], w, repeat=int(self.hparams.repeat))

    def _batch(self, windows: list[Window]) -> StageBatch:
        conds = [self._conditions(w) for w in windows] if self.n_conditions else None
        return stage_batch([self._sequence(w) for w in windows], conds)

    def _stage_windows(self, stage: str) -> list[Window]:
        self.setup()
        if stage == "predict":
            return [Window(i, 0, len(r.x)) for i, r in enumerate(self.recordings)]
        check_choice(stage, "stage", (*STAGES, "predict"))
        return self.windows[stage]

    def batches(self, stage: str) -> list[StageBatch]:
        """The batches ``(x, y, warmup, mask)`` of ``stage`` (module docstring): one full
        batch for train, val and test (none when the stage is empty); for predict one
        unpadded batch per recording, its whole sequence (all ``repeat`` periods)."""
        windows = self._stage_windows(stage)
        if stage == "predict":
            return [self._batch([w]) for w in windows]
        return [self._batch(windows)] if windows else []

    def _train_fit(self) -> FitTensors:
        """The training rows as the fits read them (:func:`stack_sequences`), built once."""
        if self._fit is None:
            self._check_varies()
            self._fit = stack_sequences([self._sequence(w) for w in self._stage_windows("train")])
        return self._fit

    def train_tensors(self) -> tuple[Tensor, Tensor]:
        """The training sequences ``(x, y)``, float64, (recordings, time), to fit
        normalizations and data-dependent operators on: each recording from its own initial
        state, right-padded with its last sample to the longest (the padding, and a longer
        warm-up than :attr:`train_warmup`, outside :attr:`train_mask`).

        Raises:
            DataFileError: the input or the target column is constant over the training
                split (ValueError for a simulation); the message names the file(s) and the
                column option (``data.input_column``, ``data.target_column``).
        """
        fit = self._train_fit()
        return fit.x, fit.y

    def train_conditions(self) -> Tensor | None:
        """The conditions (recordings, time, n) of :meth:`train_tensors`' rows, padded as
        they are (None: no condition columns)."""
        if not self.n_conditions:
            return None
        fit = self._train_fit()
        return pad_rows([self._conditions(w) for w in self._stage_windows("train")],
                        fit.x.shape[-1])

    @property
    def train_warmup(self) -> int:
        """Leading samples of :meth:`train_tensors` outside the loss and data-dependent fits."""
        return self._train_fit().warmup

    @property
    def train_mask(self) -> Tensor | None:
        """The samples of :meth:`train_tensors` the fits may use, (recordings, time) bool, or
        None (all) when the recordings share their length and warm-up."""
        return self._train_fit().mask

    def tensors(self, stage: str) -> tuple[Tensor, Tensor, int]:
        """``(x, y, warmup)`` of a stage of one sequence: (time,) tensors including the
        warm-up part (use :meth:`batches` for several recordings).

        Raises:
            ValueError: the stage holds no sequence or several.
        """
        windows = self._stage_windows(stage)
        if len(windows) != 1:
            raise ValueError(
                f"tensors({stage!r}) needs a stage of one sequence, {stage} holds "
                f"{len(windows)}: use batches({stage!r})"
            )
        return self._sequence(windows[0])

    def _loader(self, stage: str) -> DataLoader | list:
        batches = self.batches(stage)
        if not batches:
            return []
        return DataLoader(_Batches(batches), batch_size=1, shuffle=False, collate_fn=_only)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train")

    def val_dataloader(self) -> DataLoader | list:
        return self._loader("val")

    def test_dataloader(self) -> DataLoader | list:
        return self._loader("test")

    def predict_dataloader(self) -> DataLoader:
        return self._loader("predict")

    @property
    def source(self) -> str:
        """The data's file(s), or the simulation's name."""
        path = self.hparams.path
        if path is None:
            return self.hparams.simulation
        if isinstance(path, (str, Path)):
            return str(Path(path))
        return ", ".join(str(Path(p)) for p in path)
