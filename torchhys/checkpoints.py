"""The checked read of a checkpoint file: a trained network's spec (``hyper_parameters``) and
weights (``state_dict``), loaded with ``weights_only=True`` and without Lightning (``torchhys
export`` and the training commands' ``--ckpt_path`` read it; the training side's checkpoint
writer refuses the same URLs)."""

from __future__ import annotations

import os
import pickle
import re
from pathlib import Path
from typing import Any

__all__ = ["CheckpointError", "read_checkpoint", "refuse_url"]


class CheckpointError(ValueError):
    """A checkpoint file that cannot be used, naming the file and what was expected."""


_EXPECTED = "expected a checkpoint written by torchhys fit (<run>/checkpoints/last.ckpt)"
_ZIP, _PICKLE = b"PK\x03\x04", b"\x80"
_URL = re.compile(r"[A-Za-z][A-Za-z0-9+.-]+:/")
"""A URL's scheme (``http://``, ``file://``, ``s3://``; ``http:/`` once a :class:`Path` has
folded the slashes); one letter is a Windows drive (``C:/``), not a scheme."""


def refuse_url(path: str | os.PathLike, option: str = "--ckpt") -> None:
    """Raise a :class:`CheckpointError` if ``path`` is a URL (any scheme, ``file://``
    included): checkpoints are read from local files only, nothing is downloaded (a loader
    of remote files may run code from them)."""
    text = os.fspath(path)
    if _URL.match(text):
        raise CheckpointError(f"{option} {text} is a URL: torchhys reads checkpoints from "
                              "local files only (nothing is downloaded); download it and "
                              "give the local file's path")


def read_checkpoint(path: str | Path, option: str = "--ckpt", *,
                    lightning: bool = True) -> dict[str, Any]:
    """The dict saved in the checkpoint file ``path`` (``torch.load`` with
    ``weights_only=True`` on the CPU: no code from the file is run).

    Args:
        path: the file.
        option: the option that named it, for messages (``--ckpt``, ``--ckpt_path``).
        lightning: a Lightning checkpoint (a dict with ``state_dict``) is required; False:
            a plain ``torch.save``d state dict (names to tensors) is accepted too.

    Raises:
        CheckpointError: a URL (:func:`refuse_url`), no such file, not a PyTorch file,
            damaged or truncated, or not a dict of the expected kind; the message names the
            file and what was expected.
    """
    import torch

    refuse_url(path, option)
    expected = _EXPECTED + ("" if lightning else " or a torch.save'd state dict of a network")
    where = f"{option} {path}"
    file = Path(path)
    if not file.exists():
        raise CheckpointError(f"{where} does not exist; {expected}")
    if not file.is_file():
        raise CheckpointError(f"{where} is not a file; {expected}")
    with file.open("rb") as fh:
        head = fh.read(24)
    if not head:
        raise CheckpointError(f"{where} is empty; {expected}")
    if not head.startswith((_ZIP, _PICKLE)):
        start = head.decode("utf-8", "replace").split("\n")[0]
        raise CheckpointError(f"{where} is not a PyTorch file (it starts with {start!r}); "
                              f"{expected}")
    try:
        ckpt = torch.load(file, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 (whatever the loader meets in a damaged file)
        if isinstance(exc, pickle.UnpicklingError) and "weights only" in str(exc).lower():
            what = "holds objects other than tensors and plain containers"
        else:
            what = "is damaged or truncated"
        # the loader's first sentence: its advice is about trusting the file, not fixing it
        first = re.split(r"(?<=\.)\s", (str(exc).strip() or type(exc).__name__))[0]
        first = first.splitlines()[0][:120]
        raise CheckpointError(f"{where} {what} ({type(exc).__name__}: {first}); "
                              f"{expected}") from exc
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{where} holds a {type(ckpt).__name__}, not a dict; {expected}")
    if "state_dict" in ckpt:
        if not isinstance(ckpt["state_dict"], dict):
            raise CheckpointError(f"{where}: its 'state_dict' is a "
                                  f"{type(ckpt['state_dict']).__name__}, not a dict; {expected}")
    elif lightning:
        keys = ", ".join(map(repr, list(ckpt)[:5])) or "none"
        raise CheckpointError(f"{where} has no 'state_dict' (keys: {keys}); {expected}")
    elif not all(isinstance(v, torch.Tensor) for v in ckpt.values()):
        raise CheckpointError(f"{where} holds neither a 'state_dict' nor tensors only; "
                              f"{expected}")
    return ckpt
