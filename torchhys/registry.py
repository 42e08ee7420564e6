"""The registry: operators and model families by name, and where specs by name are resolved.

:data:`OPERATORS` holds the operators that specs and configs name (the built-in ones are
registered by their modules in :mod:`torchhys.operators`, the installed packages' by their
entry points, a user's by :func:`register_operator`); :func:`make_operator` builds the operator
of a spec. The protocol the operators implement is :mod:`torchhys.operator`.

:data:`FAMILIES` holds the model families that are identified on data (a spec
``{"fit": name, **options}``), each by the function that builds its placeholder and its fit
(:func:`register_family`); :data:`SEARCHES` the families' searches of their own options on a
hold-out (sign, direction, penalty, size), which the real-data benchmark's rows run, each
returning a :class:`Searched`.
"""

import importlib
import warnings
from collections.abc import Callable, Iterator, Mapping, MutableMapping
from typing import Any, NamedTuple, TypeVar

from torch import Tensor, nn

from torchhys.operator import HysteresisOperator, check_operator

__all__ = [
    "BROKEN_ENTRY_POINTS",
    "BUILTIN_FAMILIES",
    "ENTRY_POINT_GROUP",
    "EXAMPLES",
    "FAMILIES",
    "OPERATORS",
    "SEARCHES",
    "Searched",
    "load_entry_points",
    "load_families",
    "make_operator",
    "register_family",
    "register_operator",
]


OPERATORS: dict[str, Callable[..., HysteresisOperator]] = {}
"""Operators by name: ``OPERATORS[name](**options)`` builds one (see :func:`make_operator`)."""



EXAMPLES: dict[str, Callable[[], HysteresisOperator]] = {}
"""The examples given to :func:`register_operator`, by name, as given: a
:class:`torchhys.testing.Example` or a function that builds the instance (read by
:func:`torchhys.testing.example_of`)."""


def register_operator(name: str, factory: Callable[..., HysteresisOperator], *,
                      example: Callable[[], HysteresisOperator] | None = None
                      ) -> None:
    """Register an operator class (or factory) under ``name``, for specs by name.

    Registering the same factory under the same name again is a no-op (it keeps the example
    given before, unless a new one is given); so is registering a new definition of the same
    class (the same module and qualified name, as when a notebook cell that defines and
    registers it runs again), which then replaces the old one.

    Args:
        name: the name in specs and configs.
        factory: the class (or a function) that builds the operator from keyword options.
        example: a small instance for the conformance checks: a
            :class:`torchhys.testing.Example` (which builds it when called), or a function
            that builds the instance (an ``Example`` with the default settings); None:
            ``factory()`` (the default options).

    Raises:
        ValueError: ``name`` is taken by another factory.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"name must be a non-empty str, got {name!r}")
    if example is not None and not callable(example):
        raise TypeError(f"example must be an Example or a function that builds the operator, "
                        f"got {type(example).__name__}")
    old = OPERATORS.get(name, factory)
    if old is not factory and _qualified(old) != _qualified(factory):
        raise ValueError(f"operator name {name!r} is registered already ({OPERATORS[name]})")
    OPERATORS[name] = factory
    if example is not None:
        EXAMPLES[name] = example
    elif old is not factory:  # a new definition: the old example built the old class
        EXAMPLES.pop(name, None)


def _qualified(factory: object) -> tuple[str, str] | None:
    """``(module, qualified name)`` of a class or function, None for other callables."""
    module, qualname = getattr(factory, "__module__", None), getattr(factory, "__qualname__", None)
    if module is None or qualname is None or "<locals>" in qualname:
        return None
    return module, qualname


ENTRY_POINT_GROUP = "torchhys.operators"
"""The entry-point group of operators that other packages provide: the entry's name is the
operator's registered name, its value ``module:Class``."""
_entry_points_loaded = False
BROKEN_ENTRY_POINTS: dict[str, str] = {}
"""The entry points that could not be loaded or registered, by name: why (the message of
the warning :func:`load_entry_points` gave, and of the error when the name is used)."""


def load_entry_points() -> list[str]:
    """Register the operators of the installed packages' ``torchhys.operators`` entry points
    (once per process: later calls return ``[]``); called by :func:`make_operator` and by the
    training side before a name is looked up.

    A package declares one in its ``pyproject.toml``::

        [project.entry-points."torchhys.operators"]
        my_operator = "my_package.operators:MyOperator"

    An entry point that cannot be loaded (its import fails) or registered (its name is taken
    by another class) is skipped with one warning that names it and the error; the others
    are registered. Its name stays unknown: :func:`make_operator` raises a ``ValueError``
    with the same message where a spec names it (:data:`BROKEN_ENTRY_POINTS`).

    Returns:
        The names registered by this call.
    """
    global _entry_points_loaded
    if _entry_points_loaded:
        return []
    _entry_points_loaded = True
    from importlib.metadata import entry_points

    names = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            register_operator(ep.name, ep.load())
        except Exception as exc:  # noqa: BLE001 (whatever importing another package raises)
            text = " ".join(f"{type(exc).__name__}: {exc}".split())
            why = (f"entry point {ep.name!r} = {ep.value!r} of group {ENTRY_POINT_GROUP!r} "
                   f"cannot be loaded: {text}")
            BROKEN_ENTRY_POINTS[ep.name] = why
            warnings.warn(f"{why}; skipped (the other operators are registered)",
                          stacklevel=2)
            continue
        names.append(ep.name)
    return names


def make_operator(spec: Any, /, *, argument: str = "operator", **options: Any
                  ) -> HysteresisOperator:
    """The operator of a spec: the one resolver of networks, cascades and configs.

    A spec is one of:

    - a registered name, ``"eiho"``: ``OPERATORS["eiho"](**options)``;
    - a dict ``{"name": "eiho", **kwargs}``: ``OPERATORS["eiho"](**kwargs, **options)``
      (options of an operator may be specs themselves, e.g. a cascade's parts);
    - an operator (a :class:`HysteresisOperator`): itself, checked (no ``options``).

    The installed packages' entry points are registered first (:func:`load_entry_points`).

    Args:
        spec: the spec.
        argument: what the spec is called in error messages (``"operator"``,
            ``"operator[1]"``, ...).
        **options: keyword options of the operator given by name (or added to a dict's).

    Raises:
        ValueError: an unknown name (the message lists the registered ones; for the name of
            an entry point that could not be loaded, why), a dict without
            a ``name`` or with an option given twice, options the operator does not take
            (the operator's own checks name the option).
        TypeError: a spec of another type, an object outside the operator protocol, options
            given with an operator.
    """
    load_entry_points()
    if isinstance(spec, Mapping):
        if "name" not in spec:
            hint = (" ({'fit': ...} is a model family that `torchhys fit` identifies on the "
                    "training data, not an operator)" if "fit" in spec else "")
            raise ValueError(f"{argument}: a spec dict needs a 'name' (a registered operator), "
                             f"got {dict(spec)!r}{hint}")
        twice = sorted(set(spec) & set(options))
        if twice:
            raise ValueError(f"{argument}: option(s) {twice} given in the spec and as "
                             "keywords")
        name, options = spec["name"], {**{k: v for k, v in spec.items() if k != "name"},
                                       **options}
    elif isinstance(spec, str):
        name = spec
    elif isinstance(spec, nn.Module):
        if options:
            raise TypeError(f"{argument}: options {sorted(options)} apply to an operator "
                            f"given by name, not to a {type(spec).__name__} instance")
        return check_operator(spec, argument)
    else:
        raise TypeError(f"{argument} must be a registered operator name, a dict "
                        f"{{'name': NAME, **options}} or a HysteresisOperator, got "
                        f"{type(spec).__name__} {spec!r}")
    if isinstance(name, str) and name not in OPERATORS and name in BROKEN_ENTRY_POINTS:
        raise ValueError(f"{argument}: {BROKEN_ENTRY_POINTS[name]}")
    if not isinstance(name, str) or name not in OPERATORS:
        raise ValueError(f"{argument}: no operator is registered as {name!r}; registered "
                         f"names: {sorted(OPERATORS)}")
    try:
        op = OPERATORS[name](**options)
    except TypeError as e:
        raise ValueError(f"{argument} {name!r}: {e}") from e
    return check_operator(op, f"{argument} {name!r}")


BUILTIN_FAMILIES = "torchhys.identification.specs"
"""The module whose import registers the built-in families (it loads each family's module
of :mod:`torchhys.identification`, where each registers itself): loaded by name on the first
read of :data:`FAMILIES` or :data:`SEARCHES` (:func:`load_families`). The registry sits below
the families it holds and does not import them."""
_families_loaded = False

V = TypeVar("V")


def load_families() -> None:
    """Register the built-in model families (import :data:`BUILTIN_FAMILIES`), once per
    process; every read of :data:`FAMILIES` and :data:`SEARCHES` calls it first, so they
    list every family on first use without ``import torchhys`` loading them."""
    global _families_loaded
    if _families_loaded:
        return
    _families_loaded = True  # before the import: its registrations read the registry
    try:
        importlib.import_module(BUILTIN_FAMILIES)
    except BaseException:
        _families_loaded = False
        raise


class _Loaded(MutableMapping[str, V]):
    """A dict of the registry that registers the built-in families before it is read."""

    def __init__(self) -> None:
        self._items: dict[str, V] = {}

    def __getitem__(self, name: str) -> V:
        load_families()
        return self._items[name]

    def __setitem__(self, name: str, value: V) -> None:
        load_families()
        self._items[name] = value

    def __delitem__(self, name: str) -> None:
        load_families()
        del self._items[name]

    def __iter__(self) -> Iterator[str]:
        load_families()
        return iter(self._items)

    def __len__(self) -> int:
        load_families()
        return len(self._items)

    def __repr__(self) -> str:
        load_families()
        return repr(self._items)


FAMILIES: MutableMapping[str, Callable[[Mapping[str, Any]], Any]] = _Loaded()
"""Model families identified on data, by name: ``FAMILIES[name](spec)`` takes the spec
``{"fit": name, **options}`` and returns ``(placeholder, fit)``: the module that holds the
identified operator's place until the data are seen, and the function that identifies it
(see :func:`register_family`). The built-in families are registered on its first read
(:func:`load_families`)."""


class Searched(NamedTuple):
    """What a family's search returns (:data:`SEARCHES`): the options chosen on a
    time-ordered hold-out and the model they give."""

    holdout: float
    """RMS error on the hold-out (samples ``cut:`` of every row) of the chosen options,
    fitted on the samples before it."""
    options: dict[str, Any]
    """The chosen options as a spec, ``{"fit": FAMILY, **options}`` (and ``sign``: the
    target's sign the model was fitted to, where the family fits both)."""
    predict: Callable[[Tensor], Tensor]
    """The chosen options refitted on every sample: input (rows, time) -> output, in the
    units of the data searched."""
    skipped: int = 0
    """Better settings on the hold-out passed over because their refit on every sample
    failed (diverged)."""


SEARCHES: MutableMapping[str, Callable[..., Searched]] = _Loaded()
"""The families' searches of their own options, by family name:
``SEARCHES[name](x, y, warmup, cut, **grid)`` fits the family on samples before ``cut`` of
every row of ``x``, ``y`` (rows, time) for each setting of its options (the family's own
choices, such as the target's sign, the direction and the penalty, over the sizes of
``grid``), and returns a :class:`Searched`: the setting with the least RMS error on the
hold-out ``cut:``, as a spec, and its model refitted on every sample (see
:func:`register_family`). The built-in families' searches are registered on its first read
(:func:`load_families`)."""


def register_family(name: str, builder: Callable[[Mapping[str, Any]], Any], *,
                    search: Callable[..., Searched] | None = None) -> None:
    """Register a model family identified on data under ``name``, for specs
    ``{"fit": name, **options}``.

    Registering the same builder under the same name again is a no-op (a search given then
    is added). A builder from outside :mod:`torchhys.identification` registers the built-in
    families first (:func:`load_families`), so a built-in family's name is refused at once;
    the built-in ones register as their modules load.

    Args:
        name: the family's name in specs and configs.
        builder: ``builder(spec) -> (placeholder, fit)`` (see :data:`FAMILIES`).
        search: the family's search of its options on a hold-out, returning a
            :class:`Searched` (see :data:`SEARCHES`); None: none.

    Raises:
        ValueError: ``name`` is not a non-empty str, or is taken by another builder.
        TypeError: ``builder`` or ``search`` is not callable.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"family name must be a non-empty str, got {name!r}")
    if not callable(builder):
        raise TypeError(f"family {name!r}: builder must be callable (spec -> (placeholder, "
                        f"fit)), got {type(builder).__name__} {builder!r}")
    if search is not None and not callable(search):
        raise TypeError(f"family {name!r}: search must be callable or None, got "
                        f"{type(search).__name__} {search!r}")
    if not str(getattr(builder, "__module__", None) or "").startswith(
            "torchhys.identification."):
        load_families()
    families, searches = FAMILIES._items, SEARCHES._items  # type: ignore[attr-defined]
    old = families.get(name, builder)
    if old is not builder:
        raise ValueError(f"family name {name!r} is registered already ({old!r})")
    families[name] = builder
    if search is not None:
        searches[name] = search
