"""Files replaced whole or not at all (checkpoints and exported compensators).

Each new file is written to a temporary file ``.<tag>-<random>.partial`` in the folder of
its target, flushed to the disk (``fsync``) and renamed over the target with
:func:`os.replace` (atomic within a filesystem); then the folder is flushed. A reader sees
the old file or the new one, never a part. On any error before the renames (a full disk,
no permission) the temporary files are removed and the targets keep their old contents.

:func:`atomic_write_files` writes several files (the ``.h`` and ``.c`` of a C export):
every new file is complete on the disk before the first rename, so an old set is never
removed for a new one that is not whole.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Sequence

PARTIAL = ".partial"
"""Suffix of the temporary files (their names never hold "last": Lightning's
``ckpt_path="last"`` looks for files with "last" in the name)."""


def fsync_dir(folder: str) -> None:
    """Flush a folder's entries (the rename) to the disk, where the system allows it."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # a system without directory handles (Windows)
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _remove(paths: Sequence[str]) -> None:
    for temp in paths:
        try:
            os.remove(temp)
        except OSError:
            pass


def atomic_write_files(files: Sequence[tuple[str | os.PathLike, bytes]], *,
                       tag: str = "ckpt") -> None:
    """Replace each file ``path`` of ``files`` (``(path, data)`` pairs) by its ``data``.

    Every temporary file (``.<tag>-<random>.partial`` beside its target) is written and
    flushed before the first :func:`os.replace`. An error while writing removes the
    temporary files and leaves every target as it was. The new files get the permissions
    of a newly created file (``0o666`` less the umask).
    """
    targets = [os.fspath(p) for p, _ in files]
    temps: list[str] = []
    try:
        for target, (_, data) in zip(targets, files, strict=True):
            folder = os.path.dirname(os.path.abspath(target))
            temps.append(os.path.join(folder, f".{tag}-{uuid.uuid4().hex}{PARTIAL}"))
            with open(temps[-1], "xb") as fh:  # a new file: O_EXCL, 0o666 less the umask
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
        for done, (temp, target) in enumerate(zip(temps, targets, strict=True)):
            os.replace(temp, target)
            temps[done] = ""
    except BaseException:
        _remove([t for t in temps if t])
        raise
    for folder in dict.fromkeys(os.path.dirname(os.path.abspath(t)) for t in targets):
        fsync_dir(folder)


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, tag: str = "ckpt") -> None:
    """Replace the file ``path`` by ``data``, whole or not at all: the bytes go to a new
    file ``.<tag>-<random>.partial`` in the same folder, which is flushed (``fsync``) and
    renamed over ``path`` (:func:`os.replace`). On any error (a full disk, no permission)
    the temporary file is removed and ``path`` keeps its old contents. The new file gets
    the permissions of a newly created file (``0o666`` less the umask)."""
    atomic_write_files([(path, data)], tag=tag)
