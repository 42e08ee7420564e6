"""Negative numbers in scientific notation on the command lines (``--limits -5e-3 5e-3``,
``--model.lr=-1e-3`` or ``--model.lr -1e-3``).

argparse (and jsonargparse, built on it) tells a negative number from an option by a
pattern that knows ``-5`` and ``-0.005`` but not ``-5e-3``: such a value is read as an
unknown option ("expected one argument"). :func:`accept_negative_numbers` gives a parser
:data:`NEGATIVE_NUMBER` instead.
"""

from __future__ import annotations

import re
from typing import Any

__all__ = ["NEGATIVE_NUMBER", "accept_negative_numbers"]

NEGATIVE_NUMBER = re.compile(r"^-(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?$")
"""What a parser takes for a negative number, not an option: ``-5``, ``-0.005``, ``-.5``,
``-5.`` and scientific notation (``-5e-3``, ``-1E+2``)."""


def accept_negative_numbers(parser: Any) -> Any:
    """``parser`` (an ``argparse.ArgumentParser``) reading :data:`NEGATIVE_NUMBER` as values
    (argparse's own hook, ``_negative_number_matcher``, the pattern it reads them by)."""
    parser._negative_number_matcher = NEGATIVE_NUMBER
    return parser
