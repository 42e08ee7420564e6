"""Test metadata and checks of the operator protocol, for torchhys and its plugins.

:class:`Example`: a small instance of a registered operator and what the conformance checks
may expect of it, given to :func:`torchhys.registry.register_operator`.
"""

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from dataclasses import field as dataclass_field

from torchhys.operator import HysteresisOperator

__all__ = ["Example"]


@dataclass(frozen=True)
class Example:
    """A small instance of a registered operator and what the conformance tests
    (``tests/test_conformance.py``) may expect of it.

    Args:
        build: returns a new instance: a few widths or levels, for inputs in about
            ``[-1, 1]``; the tests run it in float64.
        atol: float64 tolerance between the paths that compute the same output (chunked
            calls and one call, the step and ``forward``, the exported compensator and the
            eager one), relative to the output's scale (at least 1); 0: bit for bit.
        no_gradcheck: why ``torch.autograd.gradcheck`` of ``forward`` with respect to the
            input does not apply (e.g. an output piecewise constant in it), or None.
        bad_values: state-dict keys, each with a value that breaks a constraint that
            ``load_state_dict`` checks (the whole tensor filled with it), e.g.
            ``{"weights": -1.0}`` for a non-negative density; empty where none is checked.
    """

    build: Callable[[], HysteresisOperator]
    atol: float = 0.0
    no_gradcheck: str | None = None
    bad_values: Mapping[str, float] = dataclass_field(default_factory=dict)
