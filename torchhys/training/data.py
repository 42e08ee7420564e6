"""``HysteresisDataModule``: a simulated plant, or recorded (command, response) files.

Each stage (train, val, test) is one full batch of the stage's sequences, one row per
recording (``predict``: one batch per recording, unpadded)::

    x, y     (recordings, time)   each row: ``repeat - 1`` whole periods of the recording,
                                  then its rows up to the stage's end; right-padded with
                                  the row's last sample to the longest row
    warmup   (recordings,)        index of each row's first scored sample
    mask     (recordings, time)   True on the scored samples: from ``warmup`` to the row's
                                  end (never on padding)

Every row starts from a fresh operator state (the operators are causal, so the padding
after a row cannot change it); the loss and the metrics cover the masked samples only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import lightning as L
import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from torchhys._checks import check_choice, check_int
from torchhys._finite import check_scale
from torchhys._memory import check_repeat
from torchhys.data.files import (
    Column,
    DataFileError,
    Recording,
    RecordingId,
    check_text_options,
    read_recordings,
    resolve_path,
)
from torchhys.data.splits import STAGES, Window, assign_recordings, check_split

__all__ = [
    "SIMULATIONS", "SPLIT_BY", "STAGES", "HysteresisDataModule", "SequenceDataset", "Window",
    "FitTensors", "assign_recordings", "fit_tensors", "simulate", "stack_sequences",
]

SIMULATIONS = ("paper", "fig6", "bouc_wen")
"""Simulated sources: the paper's Section 5.2 plant, its Fig. 6 plant, a Bouc-Wen plant."""
SPLIT_BY = ("time", "recording")
"""``time``: each recording split in time order; ``recording``: whole recordings per stage."""

StageBatch = tuple[Tensor, Tensor, Tensor, Tensor]
"""``(x, y, warmup, mask)`` of a stage, see the module docstring."""


def simulate(name: str, *, dt: float = 0.01, t_end: float = 8 * math.pi,
             seed: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """``(t, x, y)`` of a simulated source in float64: model input ``x`` (the plant's
    output) and target ``y`` (the plant's input), shape (time,).

    ``"bouc_wen"``: the default :class:`torchhys.plants.BoucWen` plant driven by a
    multisine (band 0.2-3 rad/s, 8 tones, random phases from ``seed``) scaled to +-6.
    """
    from torchhys.plants import bouc_wen, fig6_simulation, paper_simulation
    from torchhys.signals import multisine, time_grid, to_range

    check_choice(name, "simulation", SIMULATIONS)
    if name == "paper":
        t, u, h = paper_simulation(dt, t_end, dtype=torch.float64)
    elif name == "fig6":
        t, u, h = fig6_simulation(dt, t_end, dtype=torch.float64)
    else:  # "bouc_wen"
        t = time_grid(dt=dt, t_end=t_end, dtype=torch.float64)
        u = to_range(multisine(t, band=(0.2, 3.0), n_tones=8, seed=seed), -6.0, 6.0)
        h = bouc_wen(u, t)
    return t, h, u


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


def _pad(rows: list[Tensor], length: int) -> Tensor:
    """Rows of different lengths, each right-padded with its last value, (rows, length)."""
    return torch.stack([torch.cat([r, r[-1:].expand(length - r.numel())]) for r in rows])


class FitTensors(NamedTuple):
    """The training data that normalizations and data-dependent operators are fitted on."""

    x: Tensor
    """Input, (rows, time): one row per recording, right-padded with its last sample."""
    y: Tensor
    """Target, (rows, time), padded as x."""
    warmup: int
    """Leading samples of every row left out of the fits (their states still run)."""
    mask: Tensor | None
    """None (every sample of every row), or the samples the fits may use, (rows, time)
    bool: False on a row's padding, on a held-out block, and on the samples of a longer
    warm-up than ``warmup`` (the targets there are not used; the states run through)."""


def fit_tensors(x: Tensor, y: Tensor, first: Tensor | Sequence[int], end: Tensor | Sequence[int],
                held: Tensor | None = None) -> FitTensors:
    """:class:`FitTensors` of rows ``x``, ``y`` (rows, time) whose row r is scored from
    sample ``first[r]`` to ``end[r]`` (exclusive; padding after it), without the samples
    ``held`` ((rows, time) bool, e.g. a cross-validation block; None: none). ``warmup`` is
    the least ``first``; the mask is None when every row is whole, scored from ``warmup``
    and holds nothing out."""
    first = torch.as_tensor(first, dtype=torch.long).reshape(-1, 1)
    end = torch.as_tensor(end, dtype=torch.long).reshape(-1, 1)
    T = x.shape[-1]
    w = int(first.min())
    if bool((first == w).all()) and bool((end == T).all()) and (held is None
                                                                or not bool(held.any())):
        return FitTensors(x, y, w, None)
    t = torch.arange(T)
    mask = (t < end) & ((t < w) | (t >= first))
    if held is not None:
        mask &= ~held.to(torch.bool)
    return FitTensors(x, y, w, mask)


def stack_sequences(seqs: list[tuple[Tensor, Tensor, int]]) -> FitTensors:
    """Training sequences ``(x, y, first scored)``, each (time,), as the tensors that
    normalizations and data-dependent operators are fitted on (:class:`FitTensors`): one
    row per sequence, each from its own initial state, right-padded with its last sample
    to the longest; with a mask when their lengths or warm-ups differ."""
    length = max(s[0].numel() for s in seqs)
    return fit_tensors(_pad([s[0] for s in seqs], length), _pad([s[1] for s in seqs], length),
                       [s[2] for s in seqs], [s[0].numel() for s in seqs])


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

    Raises:
        ValueError: a bad split, ``split_by``, ``repeat``, ``warmup``, ``encoding``,
            ``delimiter`` or ``decimal`` (named ``data.<option>``); recording lists with
            ``split_by="time"``; ``run_column`` without ``path``; at :meth:`setup`, an
            empty split, an unknown recording id, too few samples in a split.
        torchhys.data.files.DataFileError: problems in a file (names file, column and
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
                decimal=hp.decimal)
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
        rec, k = self.recordings[w.index], int(self.hparams.repeat)
        x, y = torch.from_numpy(rec.x), torch.from_numpy(rec.y)
        first = max(int(self.hparams.warmup), (k - 1) * x.numel() + w.start)
        if k == 1:
            return x[: w.end], y[: w.end], first
        x, y = (torch.cat([v.repeat(k - 1), v[: w.end]]) for v in (x, y))
        return x, y, first

    def _batch(self, windows: list[Window]) -> StageBatch:
        seqs = [self._sequence(w) for w in windows]
        length = max(s[0].numel() for s in seqs)
        steps = torch.arange(length)
        mask = torch.stack([(steps >= first) & (steps < x.numel()) for x, _, first in seqs])
        return (_pad([s[0] for s in seqs], length), _pad([s[1] for s in seqs], length),
                torch.tensor([s[2] for s in seqs]), mask)

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
