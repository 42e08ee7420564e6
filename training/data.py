"""``HysteresisDataModule``: a simulated plant or a recorded (command, response) file."""

from __future__ import annotations

import math
from pathlib import Path

import lightning as L
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from torchhys._checks import check_choice, check_int
from torchhys.training.files import Column, DataFileError, read_record

__all__ = ["SIMULATIONS", "HysteresisDataModule", "SequenceDataset", "simulate"]

SIMULATIONS = ("paper", "fig6", "bouc_wen")
"""Simulated sources: the paper's Section 5.2 plant, its Fig. 6 plant, a Bouc-Wen plant."""


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


def _check_split(split: str | list[float] | tuple[float, ...]) -> tuple[float, float, float]:
    if split == "paper":
        return (1.0, 1.0, 1.0)
    if isinstance(split, str) or len(split) != 3:
        raise ValueError(
            f"split must be 'paper' or three fractions [train, val, test], got {split!r}"
        )
    fr = tuple(float(f) for f in split)
    if not (fr[0] > 0 and min(fr) >= 0 and sum(fr) <= 1.0 + 1e-9):
        raise ValueError(
            f"split fractions must be >= 0 with train > 0 and sum <= 1, got {list(split)}"
        )
    return fr  # type: ignore[return-value]


class HysteresisDataModule(L.LightningDataModule):
    """Full-sequence data for inverse-hysteresis training.

    The source is a simulated plant (``simulation``, by default the paper's Section 5.2:
    input ``h = H[x]``, target ``x``) unless ``path`` names a recorded CSV or NPZ file.
    Each stage sees one sequence per step (full batch): the split is time-ordered, and the
    validation and test sequences carry the preceding record as warm-up (so operator
    states continue as in deployment; metrics cover the split's own samples only).

    Args:
        path: a recorded ``.csv``/``.npz`` file (see :func:`torchhys.training.files.read_record`),
            or None for a simulation.
        input_column: column of the model input (the plant's response), name or index.
        target_column: column of the model target (the command), name or index.
        time_column: optional column of sample times (checked to increase).
        simulation: ``"paper"``, ``"fig6"`` or ``"bouc_wen"`` when ``path`` is None.
        dt: sampling step of the simulation.
        t_end: end time of the simulation.
        seed: seed of the simulation's random signal (``"bouc_wen"``).
        split: ``"paper"`` (the whole record for train, validation and test, as the
            paper reports training MSE) or fractions ``[train, val, test]`` (sum <= 1).
        min_samples: fewest samples per non-empty split.
        warmup: leading samples of the record left out of the training loss and of the
            fits of data-dependent operators (with ``split="paper"`` also of the metrics):
            the model's operators start from a zero state, a recorded plant from its own,
            so the first samples after the start disagree (states still run through them).

    Raises:
        ValueError: a bad split, too few samples in a split.
        torchhys.training.files.DataFileError: problems in the file (names file, column and row).
    """

    def __init__(
        self, *, path: str | None = None, input_column: Column = "response",
        target_column: Column = "command", time_column: Column | None = None,
        simulation: str = "paper", dt: float = 0.01, t_end: float = 8 * math.pi,
        seed: int = 0, split: str | list[float] = "paper", min_samples: int = 16,
        warmup: int = 0,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.fractions = _check_split(split)
        check_int(warmup, "warmup", minimum=0)
        if path is None:
            check_choice(simulation, "simulation", SIMULATIONS)
        self.t: Tensor | None = None
        self.x: Tensor | None = None
        self.y: Tensor | None = None
        self.bounds: dict[str, tuple[int, int]] = {}

    # -----------------------------------------------------------------------------------
    def _load(self) -> None:
        hp = self.hparams
        if hp.path is None:
            self.t, self.x, self.y = simulate(hp.simulation, dt=hp.dt, t_end=hp.t_end,
                                              seed=hp.seed)
        else:
            rec = read_record(hp.path, input_column=hp.input_column,
                              target_column=hp.target_column, time_column=hp.time_column,
                              min_samples=hp.min_samples)
            self.x, self.y = torch.from_numpy(rec.x), torch.from_numpy(rec.y)
            self.t = None if rec.t is None else torch.from_numpy(rec.t)
        n = self.x.numel()
        if self.hparams.split == "paper":
            self.bounds = {"train": (0, n), "val": (0, n), "test": (0, n)}
        else:
            ends = [round(n * sum(self.fractions[: i + 1])) for i in range(3)]
            starts = [0, ends[0], ends[1]]
            stages = ("train", "val", "test")
            self.bounds = {s: (a, b) for s, a, b in zip(stages, starts, ends, strict=True)}
        for stage, (a, b) in self.bounds.items():
            if 0 < b - a < hp.min_samples or (stage == "train" and b - a < hp.min_samples):
                where = hp.path if hp.path is not None else f"simulation {hp.simulation!r}"
                err = DataFileError if hp.path is not None else ValueError
                raise err(
                    f"{where}: the {stage} split holds {b - a} samples (rows {a}..{b - 1} of "
                    f"{n}), at least {hp.min_samples} are needed; record more data or change "
                    f"split={list(self.fractions) if hp.split != 'paper' else 'paper'}"
                )
        a, b = self.bounds["train"]
        if b - a - hp.warmup < hp.min_samples:
            where = hp.path if hp.path is not None else f"simulation {hp.simulation!r}"
            raise ValueError(
                f"{where}: warmup={hp.warmup} leaves {b - a - hp.warmup} of the {b - a} "
                f"training samples, at least {hp.min_samples} are needed; lower warmup"
            )

    def prepare_data(self) -> None:
        """Nothing to download: data are simulated or read in :meth:`setup`."""

    def setup(self, stage: str | None = None) -> None:
        if self.x is None:
            self._load()

    def train_tensors(self) -> tuple[Tensor, Tensor]:
        """The training part ``(x, y)``, each (1, time), float64: fit normalizations on it
        (its first :attr:`train_warmup` samples are the warm-up)."""
        self.setup()
        a, b = self.bounds["train"]
        return self.x[a:b].unsqueeze(0), self.y[a:b].unsqueeze(0)

    @property
    def train_warmup(self) -> int:
        """Leading samples of :meth:`train_tensors` outside the loss and data-dependent fits."""
        return int(self.hparams.warmup)

    def tensors(self, stage: str) -> tuple[Tensor, Tensor, int]:
        """``(x, y, warmup)`` of ``stage``: (time,) tensors including the warm-up part."""
        self.setup()
        if stage == "predict":
            return self.x, self.y, 0
        a, b = self.bounds[stage]
        if stage == "train" or self.hparams.split == "paper":
            return self.x[a:b], self.y[a:b], self.train_warmup
        return self.x[:b], self.y[:b], a  # the preceding record is the warm-up

    def _loader(self, stage: str) -> DataLoader | list:
        a, b = self.bounds.get(stage, (0, 1)) if stage != "predict" else (0, 1)
        if b <= a:
            return []
        x, y, warm = self.tensors(stage)
        return DataLoader(SequenceDataset(x, y, warm), batch_size=1, shuffle=False)

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
        return str(Path(self.hparams.path)) if self.hparams.path else self.hparams.simulation
