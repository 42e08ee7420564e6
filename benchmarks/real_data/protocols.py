"""The protocols by name (:data:`DATASETS`), the optional files they read (:class:`Files`),
and the short and long variants of a protocol's training part."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from .datasets import (
    FERRITE,
    PIEZO,
    QUAD,
    SEALS,
    Split,
    ferrite,
    forc,
    friction_damper,
    jamodel,
    micromanipulator,
    mr_damper,
    piezo,
    pneumatic,
    quad,
    quad_files,
    sma,
)


def shortened(split: Split, n: int = 50, *, stride: bool = False,
              every: int | None = None) -> Split:
    """A short record of about ``n`` scored training samples: the first training row, its
    warm-up and the ``n`` samples after it (a short log of the device), or with ``stride``
    every k-th sample of every training row (a closed loop sampled coarsely: its shape kept),
    or with ``every = k`` every k-th sample of each training row's warm-up and of the ``n k``
    samples after it (a short log at 1/k of the rate: where k-th samples of the whole row
    would skip most of each period). The held-out recordings are unchanged."""
    if every is not None:
        if stride or every < 1:
            raise ValueError(f"shortened: every must be a positive int without stride, got "
                             f"every={every}, stride={stride}")
        cut = split.warmup + n * every
        return split._replace(x=split.x[:, :cut:every], y=split.y[:, :cut:every],
                              warmup=-(-split.warmup // every))
    if not stride:
        return split._replace(x=split.x[:1, :split.warmup + n],
                              y=split.y[:1, :split.warmup + n])
    k = max(1, split.y[:, split.warmup:].numel() // n)
    return split._replace(x=split.x[:, ::k], y=split.y[:, ::k], warmup=-(-split.warmup // k))


def tiled(split: Split, total: int = 100_000) -> Split:
    """A long record: each training row repeated end to end until the rows hold ``total``
    scored samples in all (a test of scale and run time: no new information)."""
    rows, T = split.x.shape
    reps = -(-(total // rows + split.warmup) // T)
    return split._replace(x=split.x.repeat(1, reps), y=split.y.repeat(1, reps))


class Files(NamedTuple):
    """The data files read from options (the others are in ``examples/data/real/``)."""

    ferrite: Path = FERRITE
    piezo: Path = PIEZO
    quad: Path = QUAD

    def missing(self, need: str) -> list[Path]:
        """The files that option ``need`` names (for ``quad``: the run files in its folder)
        and that are not there."""
        path = getattr(self, need)
        paths = list(quad_files(path).values()) if need == "quad" else [path]
        return [p for p in paths if not p.is_file()]


class Protocol(NamedTuple):
    """A data set's protocol."""

    about: str
    """What is fitted to what, and what is held out."""
    build: Callable[[Files], Split]
    """The builder of its split from the optional files."""
    needs: str | None = None
    """The option (a :class:`Files` field) whose file it reads; None: shipped files only."""


DATASETS: dict[str, Protocol] = {name: Protocol(*entry) for name, entry in {
    # name: (about, build[, the option whose file it reads])
    "mnzn_ferrite": ("B -> H, loops 0+3 / 1+2", lambda f: ferrite(f.ferrite, [0, 3], [1, 2]),
                     "ferrite"),
    "mnzn_ferrite_largest": ("B -> H, loop 3 / 0+1+2",
                             lambda f: ferrite(f.ferrite, [3], [0, 1, 2]), "ferrite"),
    "m130_steel": ("B -> H, loops 0+2 / 1", lambda f: jamodel([0, 2], [1])),
    "m130_steel_largest": ("B -> H, loop 2 / 0+1", lambda f: jamodel([2], [0, 1])),
    "mnzn_hp_ferrite": ("B -> H, loops 4+7 / 5+6", lambda f: jamodel([4, 7], [5, 6])),
    "mnzn_hp_ferrite_largest": ("B -> H, loop 7 / 4+5+6", lambda f: jamodel([7], [4, 5, 6])),
    "mr_damper_0V": ("position -> force, even / odd", lambda f: mr_damper(0.0)),
    "mr_damper_0.87V": ("position -> force, even / odd", lambda f: mr_damper(0.8712)),
    "mr_damper_1.98V": ("position -> force, even / odd", lambda f: mr_damper(1.98)),
    "mr_damper_3.21V": ("position -> force, even / odd", lambda f: mr_damper(3.212)),
    "friction_damper": ("displacement -> force, sines / earthquakes",
                        lambda f: friction_damper()),
    "friction_damper_sines": ("displacement -> force, 1 in sines / 0.5 and 1.5 in sines",
                              lambda f: friction_damper((1, 4, 7), (0, 2, 3, 5, 6, 8, 9))),
    "friction_damper_36lb_sines": ("as friction_damper_sines, at a band tension of 36 lb",
                                   lambda f: friction_damper(
                                       (1, 4, 7), (0, 2, 3, 5, 6, 8, 9),
                                       file="friction_damper_backlash_brfd_36lb.csv")),
    "pneumatic_oring": ("position -> friction, 1+7 / 3+5 bar", lambda f: pneumatic()),
    **{f"pneumatic_{k}": (f"position -> friction of the {v} seal, 1+7 / 3+5 bar",
                          lambda f, k=k: pneumatic(k)) for k, v in SEALS.items()},
    "sma_actuator": ("temperature -> extension, cycles 1-4 / 5-7", lambda f: sma()),
    "feco_forc": ("field -> moment, reversal curves 0, 2, 4, ... / 1, 3, 5, ...",
                  lambda f: forc()),
    "mnzn_ferrite_short": ("mnzn_ferrite, training loops sampled every 5th: 52 samples",
                           lambda f: shortened(ferrite(f.ferrite, [0, 3], [1, 2]), stride=True),
                           "ferrite"),
    "mr_damper_0V_short": ("mr_damper_0V, the first 50 scored samples of one training row",
                           lambda f: shortened(mr_damper(0.0))),
    "pneumatic_oring_short": ("pneumatic_oring, the first 50 samples of the 1 bar record",
                              lambda f: shortened(pneumatic())),
    "pneumatic_oring_long": ("pneumatic_oring, training rows tiled to 1e5 samples",
                             lambda f: tiled(pneumatic())),
    "piezo_actuator": ("displacement -> voltage, t < 7 s / t >= 7 s (one record, --piezo)",
                       lambda f: piezo(f.piezo, compensator=True), "piezo"),
    "piezo_actuator_forward": ("voltage -> displacement, as piezo_actuator",
                               lambda f: piezo(f.piezo, compensator=False), "piezo"),
    "piezo_actuator_short": ("piezo_actuator, the training part sampled every 370th: 50 samples",
                             lambda f: shortened(piezo(f.piezo, compensator=True), stride=True),
                             "piezo"),
    "piezo_manipulator": ("displacement -> voltage, identification record / test record",
                          lambda f: micromanipulator(compensator=True)),
    "piezo_manipulator_forward": ("voltage -> displacement, as piezo_manipulator",
                                  lambda f: micromanipulator(compensator=False)),
    "piezo_manipulator_short": ("piezo_manipulator, one period of the training record at 50 Hz: "
                                "50 samples",
                                lambda f: shortened(micromanipulator(compensator=True), every=4)),
    "quad_magnet": ("integrated gradient -> current, major loop / minor loops (--quad)",
                    lambda f: quad(f.quad, compensator=True), "quad"),
    "quad_magnet_forward": ("current -> integrated gradient, as quad_magnet",
                            lambda f: quad(f.quad, compensator=False), "quad"),
}.items()}
"""Data sets by name: their protocol, the builder of its split and the option it reads."""
