"""``--quiet``: no progress lines, in the command's process and in those it starts (the
ranks of a multi-process run, the processes of ``model.select_jobs``), which read
``TORCHHYS_QUIET``."""

from __future__ import annotations

import os

__all__ = ["QUIET_ENV", "QUIET_FLAG", "quiet_requested"]

QUIET_FLAG = "--quiet"
"""The command-line flag."""
QUIET_ENV = "TORCHHYS_QUIET"
"""The environment variable it sets (progress off when set to anything but '', '0', 'false'
or 'no')."""


def quiet_requested() -> bool:
    """Whether progress output is off (``--quiet`` sets ``TORCHHYS_QUIET``)."""
    return os.environ.get(QUIET_ENV, "").strip().lower() not in ("", "0", "false", "no")
