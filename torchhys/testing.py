"""Test metadata and checks of the operator protocol, for torchhys and its plugins.

:class:`Example`: a small instance of a registered operator and what the conformance checks
may expect of it, given to :func:`torchhys.registry.register_operator`; :func:`example_of`:
the example of a registered name.
"""

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from dataclasses import field as dataclass_field

import torchhys.registry as registry
from torchhys.operator import HysteresisOperator

__all__ = ["Example", "example_of"]


@dataclass(frozen=True)
class Example:
    """A small instance of a registered operator and what the conformance tests
    (``tests/test_conformance.py``) may expect of it. Calling it builds the instance.

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

    def __call__(self) -> HysteresisOperator:
        return self.build()


def example_of(name: str) -> Example:
    """The :class:`Example` of the operator registered as ``name``: the one given to
    :func:`~torchhys.registry.register_operator` (a function given there: an ``Example``
    with the default settings), else ``Example(OPERATORS[name])`` (its default options).

    Raises:
        KeyError: an unknown name.
    """
    if name not in registry.OPERATORS:
        raise KeyError(f"no operator is registered as {name!r}")
    given = registry.EXAMPLES.get(name) or registry.OPERATORS[name]
    return given if isinstance(given, Example) else Example(given)
