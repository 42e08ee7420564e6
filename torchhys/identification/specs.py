"""Operators of the expanded input space from config specs: registered operators and the
model families fitted on the training data.

A spec of ``model.operator`` is one of:

- an operator spec of :func:`torchhys.registry.make_operator`: a registered name (``"eiho"``,
  ``"zhao_tan"``: the module's ``operator_kwargs`` apply) or a dict ``{"name": NAME,
  **kwargs}`` of any operator in :data:`torchhys.registry.OPERATORS` (``"eiho"``,
  ``"backlash"``, ``"preisach"``, ``"cascade"``, whatever a user registers with
  :func:`torchhys.registry.register_operator`), built as it stands;
- a model family fitted on the training split when fitting starts, ``{"fit": FAMILY,
  **options}`` (:data:`FIT_FAMILIES`):

  - ``{"fit": "plays", "n": 16, "power": 1.0, "span_fraction": 1.0, "learnable": False}``:
    :class:`torchhys.Backlash` of the input, full widths
    ``span_fraction * span(x_train) (k / n)^power``, ``k = 1..n`` (or explicit ``widths``:
    nothing to fit);
  - ``{"fit": "pi_ls", "n_widths": 30, "power": 3.0, "ridge": 0.0, "learnable": False}``:
    the least-squares Prandtl-Ishlinskii model of the target from the input
    (:func:`torchhys.identification.fitting.fit_prandtl_ishlinskii` on
    :func:`~torchhys.identification.fitting.play_width_grid`);
  - ``pi_nonneg``, ``gpi``, ``preisach``, ``stop_pi``, ``jiles_atherton``, ``drift``:
    constrained model families (:mod:`torchhys.identification.families`).

  ``{"fit": "preisach"}`` is the Preisach model identified on the data; ``{"name":
  "preisach"}`` the registered operator with the options given.

All of them are causal except ``eiho_segment``. A family is built as a
placeholder of the right shape and fitted by :func:`fit_data_dependent` on the training
split; its widths and weights are buffers (or parameters) of the network, so checkpoints and
exports carry them.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchhys import Backlash, PrandtlIshlinskii
from torchhys._checks import (
    check_int,
    check_nonnegative,
    check_positive,
    check_warmup,
    fitted_samples,
)
from torchhys.identification._fit_cache import shared
from torchhys.identification.families import FAMILIES
from torchhys.identification.fitting import fit_prandtl_ishlinskii, play_width_grid
from torchhys.operator import HysteresisOperator
from torchhys.registry import make_operator

__all__ = ["FIT_FAMILIES", "OperatorSpec", "build_operators", "fit_data_dependent"]

OperatorSpec = str | Mapping[str, Any] | HysteresisOperator
"""``"eiho"``, ``{"name": NAME, **kwargs}``, ``{"fit": FAMILY, **options}`` or an
operator."""

Fitter = Callable[[Tensor, Tensor, int, Tensor | None], nn.Module]
"""Builds the fitted operator from the training input and target, (batch, time) each, the
number of leading warm-up samples to leave out of the fit, and the mask of the samples to use
((batch, time) bool, False: a held-out block or a shorter row's padding, the states running
through them; None: all)."""


def _positive_int(spec: Mapping[str, Any], key: str, default: int) -> int:
    return check_int(spec.get(key, default), f"fit {spec['fit']!r}: {key}", minimum=1)


def _check_keys(spec: Mapping[str, Any], allowed: set[str]) -> None:
    unknown = sorted(set(spec) - allowed - {"fit"})
    if unknown:
        raise ValueError(
            f"fit {spec['fit']!r}: unknown option(s) {unknown}; valid: {sorted(allowed)}"
        )


def _flag(spec: Mapping[str, Any], key: str) -> bool:
    value = spec.get(key, False)
    if not isinstance(value, bool):
        raise ValueError(f"fit {spec['fit']!r}: {key} must be true or false, got {value!r}")
    return value


def _known(x: Tensor, mask: Tensor | None) -> Tensor:
    """The samples of x (batch, time) in ``mask`` (None: all)."""
    return x if mask is None else x[mask]


def _plays(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter | None]:
    _check_keys(spec, {"n", "power", "span_fraction", "learnable", "widths"})
    learnable = _flag(spec, "learnable")
    if spec.get("widths") is not None:
        widths = torch.as_tensor(spec["widths"], dtype=torch.get_default_dtype())
        return Backlash(widths, learnable=learnable), None
    n = _positive_int(spec, "n", 16)
    power = check_positive(spec.get("power", 1.0), "fit 'plays': power")
    fraction = check_positive(spec.get("span_fraction", 1.0), "fit 'plays': span_fraction")

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        return Backlash(fraction * play_width_grid(_known(x, mask), n, power=power),
                        learnable=learnable)

    return Backlash(torch.arange(1, n + 1) / n, learnable=learnable), fit


def _pi_ls(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _check_keys(spec, {"n_widths", "power", "ridge", "learnable"})
    n = _positive_int(spec, "n_widths", 30)
    power = check_positive(spec.get("power", 3.0), "fit 'pi_ls': power")
    ridge = check_nonnegative(spec.get("ridge", 0.0), "fit 'pi_ls': ridge")
    learnable = _flag(spec, "learnable")

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        widths = play_width_grid(_known(x, mask), n, power=power)
        return fit_prandtl_ishlinskii(x, y, widths, ridge=ridge, learnable=learnable,
                                      warmup=warmup, mask=mask)

    placeholder = PrandtlIshlinskii(torch.arange(1, n + 1) / n, torch.zeros(n),
                                    learnable=learnable)
    return placeholder, fit


FIT_FAMILIES: dict[str, Callable[[Mapping[str, Any]], tuple[nn.Module, Fitter | None]]] = {
    "plays": _plays,
    "pi_ls": _pi_ls,
    **FAMILIES,
}
"""The model families of the specs ``{"fit": FAMILY, **options}``, by name: each builder
takes the spec and returns ``(placeholder module, fitter or None)``."""


def _build(spec: object, argument: str, operator_kwargs: Mapping[str, Any]
           ) -> tuple[nn.Module, Fitter | None]:
    """One spec's module and fitter (None: nothing to fit)."""
    if isinstance(spec, Mapping) and "fit" in spec:
        family = spec["fit"]
        if "name" in spec:
            raise ValueError(f"{argument}: a spec has either 'name' (a registered operator) "
                             f"or 'fit' (a model family), got both: {dict(spec)!r}")
        if not isinstance(family, str) or family not in FIT_FAMILIES:
            raise ValueError(f"{argument}: no model family is called {family!r}; families: "
                             f"{sorted(FIT_FAMILIES)}")
        module, fitter = FIT_FAMILIES[family](spec)
        return module, None if fitter is None else shared(spec, fitter)
    if isinstance(spec, Mapping) and "name" not in spec:
        raise ValueError(f"{argument}: a spec dict needs a 'name' (a registered operator) or "
                         f"a 'fit' (a model family: {sorted(FIT_FAMILIES)}), got {dict(spec)!r}")
    try:
        return make_operator(spec, argument=argument,
                             **operator_kwargs if isinstance(spec, str) else {}), None
    except (ValueError, TypeError) as err:
        name = spec if isinstance(spec, str) else (
            spec.get("name") if isinstance(spec, Mapping) else None)
        if isinstance(name, str) and name in FIT_FAMILIES:
            raise type(err)(f"{err} (the model family fitted on the training data is "
                            f"written {{fit: {name}, ...}})") from None
        raise


def build_operators(
    operator: OperatorSpec | Sequence[OperatorSpec] | None,
    operator_kwargs: Mapping[str, Any] | None = None,
) -> tuple[list[nn.Module], dict[int, Fitter]]:
    """Operator modules of a spec (or list of specs), and fitters of the model families.

    Args:
        operator: a spec, a list of specs, or None (no operator: the plain network).
        operator_kwargs: keyword arguments of the operators given by name alone
            (``"eiho"``).

    Returns:
        ``(modules, fitters)``: ``fitters[i]`` builds the fitted ``modules[i]`` from training
        data (see :func:`fit_data_dependent`).

    Raises:
        ValueError: an unknown operator or family name (the message lists the valid ones),
            a dict with neither or both of ``name`` and ``fit``, unknown or bad options.
        TypeError: a spec that is neither a name, a dict nor an operator.
    """
    if operator is None:
        return [], {}
    several = isinstance(operator, (list, tuple))
    specs = list(operator) if several else [operator]
    modules, fitters = [], {}
    for i, spec in enumerate(specs):
        module, fitter = _build(spec, f"operator[{i}]" if several else "operator",
                                operator_kwargs or {})
        modules.append(module)
        if fitter is not None:
            fitters[i] = fitter
    return modules, fitters


@torch.no_grad()
def fit_data_dependent(operators: nn.ModuleList, fitters: Mapping[int, Fitter], x: Tensor,
                       y: Tensor, *, warmup: int = 0, mask: Tensor | None = None) -> None:
    """Fit the data-dependent operators in place on training data (physical units).

    The fitted module's state (widths, weights) is copied into ``operators[i]``, in that
    module's dtype and device, so the network's structure, and its checkpoints, stay as
    built.

    Args:
        operators: the network's operators.
        fitters: from :func:`build_operators`.
        x: training input, (batch, time); y: training target, same shape.
        warmup: leading samples left out of least-squares fits (states run through them).
        mask: the samples the fits may use, bool, the shape of x (False: a held-out block of
            a cross-validation, a shorter recording's padding; the states run through them,
            their targets are not used); None: all.

    Raises:
        ValueError: ``warmup`` not smaller than the number of samples, a bad mask.
    """
    check_warmup(warmup, x.shape[-1])
    xb, yb = x.reshape(-1, x.shape[-1]), y.reshape(-1, y.shape[-1])
    if mask is not None:
        mask = fitted_samples(mask, (xb.shape[0], xb.shape[1]), 0)
    for i, fit in fitters.items():
        target = operators[i]
        ref = next(iter(target.state_dict().values()))
        fitted = fit(xb.to(torch.float64), yb.to(torch.float64), warmup, mask)
        state = {k: v.to(ref.dtype) for k, v in fitted.state_dict().items()}
        target.load_state_dict(state)
