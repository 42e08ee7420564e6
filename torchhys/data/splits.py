"""Stage splits: which part of which recording each stage (train, val, test) scores.

:class:`Window` is a stage's part of one recording; :func:`check_split` checks the split
fractions and :func:`assign_recordings` gives whole recordings to the stages
(``split_by="recording"``). Used by :class:`~torchhys.training.HysteresisDataModule`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

from torchhys.data.tables import RecordingId, recording_id

__all__ = ["STAGES", "Window", "assign_recordings", "check_split"]

STAGES = ("train", "val", "test")


class Window(NamedTuple):
    """A stage's part of a recording: rows ``[start, end)`` are scored; the rows before
    ``start`` (and the warm-up periods of ``repeat``) only run the operator states."""

    index: int
    """Position of the recording in :attr:`HysteresisDataModule.recordings`."""
    start: int
    end: int


def check_split(split: str | list[float] | tuple[float, ...]) -> tuple[float, float, float]:
    """The fractions ``(train, val, test)`` of ``split`` (``"paper"``: 1, 1, 1: every stage
    the whole record).

    Raises:
        ValueError: not ``"paper"`` nor three fractions >= 0 with train > 0 and sum <= 1.
    """
    if split == "paper":
        return (1.0, 1.0, 1.0)
    if isinstance(split, str) or len(split) != 3:
        raise ValueError(
            f"split must be 'paper' or three fractions [train, val, test], got {split!r}"
        )
    if any(isinstance(f, bool) or not isinstance(f, (int, float)) for f in split):
        raise ValueError(f"split fractions must be numbers, got {list(split)}")
    fr = tuple(float(f) for f in split)
    if not (fr[0] > 0 and min(fr) >= 0 and sum(fr) <= 1.0 + 1e-9):
        raise ValueError(
            f"split fractions must be >= 0 with train > 0 and sum <= 1, got {list(split)}"
        )
    return fr  # type: ignore[return-value]


def _pick(ids: list[RecordingId], given: Sequence[RecordingId], arg: str,
          where: str) -> list[int]:
    """Positions of the listed recordings."""
    if isinstance(given, (str, int)) or not isinstance(given, Sequence):
        raise TypeError(f"{arg} must be a list of recording ids, got {given!r}")
    picked: list[int] = []
    for g in given:
        rid = recording_id(g)
        if rid not in ids:
            raise ValueError(f"{arg}: unknown recording {g!r}; the recordings of {where} are {ids}")
        if ids.index(rid) in picked:
            raise ValueError(f"{arg}: recording {g!r} is listed twice in {list(given)}")
        picked.append(ids.index(rid))
    return picked


def assign_recordings(
    ids: list[RecordingId], split: str | Sequence[float],
    lists: dict[str, Sequence[RecordingId] | None], *, where: str = "the data",
) -> dict[str, list[int]]:
    """Positions of the recordings of each stage when whole recordings are split.

    A stage with a list (``lists["val"]``) gets those recordings. With ``split="paper"``,
    train gets every recording not listed for val or test (all of them when nothing is
    listed), and val and test get the training ones unless listed. With fractions, the
    recordings in no list are divided in order among the stages without a list, each
    getting its fraction of what the listed stages leave (``round`` of cumulative shares,
    as in the time split).

    Args:
        ids: the recordings' ids, in order.
        split: ``"paper"`` or fractions ``[train, val, test]`` (sum <= 1).
        lists: ``{"train": ids or None, "val": ..., "test": ...}`` (None: not listed).
        where: the data's name in messages (its files).

    Returns:
        ``{"train": positions in ids, "val": ..., "test": ...}``.

    Raises:
        ValueError: an unknown or repeated id, an id listed for train and for val or test
            (unless ``split="paper"``), a bad split, no training recording, or a stage with
            a positive fraction that gets no recording (an empty split).
        TypeError: a ``lists`` entry that is neither None nor a list.
    """
    fractions = check_split(split)
    chosen = {s: _pick(ids, lists[s], f"{s}_recordings", where)
              for s in STAGES if lists.get(s) is not None}
    for stage in ("val", "test"):  # split="paper" evaluates on training recordings
        both = [ids[i] for i in chosen.get(stage, []) if i in chosen.get("train", [])]
        if both and split != "paper":
            raise ValueError(
                f"{where}: recording(s) {both} are listed in train_recordings and in "
                f"{stage}_recordings; a held-out recording must not be trained on (split="
                "'paper' evaluates on training recordings)")
    if split == "paper":
        held_out = {i for s in ("val", "test") for i in chosen.get(s, [])}
        chosen.setdefault("train", [i for i in range(len(ids)) if i not in held_out])
        for stage in ("val", "test"):
            chosen.setdefault(stage, list(chosen["train"]))
    else:
        used = {i for picked in chosen.values() for i in picked}
        rest = [i for i in range(len(ids)) if i not in used]
        share = 1.0 - sum(f for s, f in zip(STAGES, fractions, strict=True) if s in chosen)
        cum = 0.0
        for stage, f in zip(STAGES, fractions, strict=True):
            if stage in chosen:
                continue
            a = round(len(rest) * cum / share) if share > 1e-12 else 0
            cum += f
            b = min(round(len(rest) * cum / share), len(rest)) if share > 1e-12 else 0
            chosen[stage] = rest[a:b]
            if f > 0 and a >= b:
                left = " left by the listed stages" if len(rest) < len(ids) else ""
                raise ValueError(
                    f"{where}: split={list(fractions)} gives the {stage} split none of the "
                    f"{len(rest)} recordings{left} ({ids}); list them with "
                    f"{stage}_recordings, or set its fraction to 0"
                )
    if not chosen["train"]:
        raise ValueError(
            f"{where}: the train split holds no recording; list some with train_recordings "
            f"(the recordings are {ids})"
        )
    return {s: chosen[s] for s in STAGES}
