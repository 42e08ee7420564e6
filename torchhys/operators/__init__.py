"""Hysteresis operators: each family's module, its streaming step(s) and its inverse.

Every operator here subclasses :class:`torchhys.operator.HysteresisOperator` and is
registered by name in :data:`torchhys.registry.OPERATORS` when its module is imported.
The pure tensor maths behind each family lives in :mod:`torchhys.functional`.
"""

from torchhys.operators import linear  # noqa: F401 (registers the linear blocks of torchhys.dynamics)
