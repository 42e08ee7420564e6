"""Operators of the expanded input space from config specs: registered operators and the
model families fitted on the training data.

A spec of ``model.operator`` is one of:

- an operator spec of :func:`torchhys.registry.make_operator`: a registered name (``"eiho"``,
  ``"zhao_tan"``: the module's ``operator_kwargs`` apply) or a dict ``{"name": NAME,
  **kwargs}`` of any operator in :data:`torchhys.registry.OPERATORS` (``"eiho"``,
  ``"backlash"``, ``"preisach"``, ``"cascade"``, whatever a user registers with
  :func:`torchhys.registry.register_operator`), built as it stands;
- a model family fitted on the training split when fitting starts, ``{"fit": FAMILY,
  **options}``, a family of :data:`torchhys.registry.FAMILIES`; the built-in ones are
  registered and documented beside their fits:

  - ``plays``, ``pi_ls``, ``pi_nonneg``: the Prandtl-Ishlinskii families
    (:mod:`torchhys.identification.prandtl_ishlinskii`);
  - ``gpi``: :mod:`torchhys.identification.generalized_pi`;
  - ``preisach``: :mod:`torchhys.identification.preisach`;
  - ``stop_pi``: :mod:`torchhys.identification.stop_pi`;
  - ``jiles_atherton``: :mod:`torchhys.identification.jiles_atherton`;
  - ``drift``: :mod:`torchhys.identification.drift`.

  ``{"fit": "preisach"}`` is the Preisach model identified on the data; ``{"name":
  "preisach"}`` the registered operator with the options given.

All of them are causal except ``eiho_segment``. A family is built as a
placeholder of the right shape and fitted by :func:`fit_data_dependent` on the training
split; its widths and weights are buffers (or parameters) of the network, so checkpoints and
exports carry them.

The constrained families (all but ``plays`` and ``pi_ls``) build an operator whose output is
a fitted model of the target (in standardized units; ``jiles_atherton`` in the target's
physical units); the network that reads it (``hidden: 1, activation: identity`` for a plain
affine readout, whose normalization standardizes the operator's output) maps it back. They
are the candidates of ``configs/measured.yaml`` and ``configs/magnetic.yaml``.
``ridge``/``smoothness: "auto"`` picks the penalty on a time-ordered hold-out inside the
training split (the last quarter of each row's scored samples;
:func:`~torchhys.identification.fitting.select_pi_ridge`,
:func:`~torchhys.identification.preisach.select_penalty`). Every choice uses the training
split only. Widths come from :func:`~torchhys.identification.fitting.play_width_grid` of the
fitted model's input. A fit that cannot exist (no inverse, a target that does not rise, a
diverged fit) raises :class:`~torchhys.identification.errors.FitError`: model selection
scores that candidate as failed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._checks import check_warmup, fitted_samples
from torchhys.identification import (
    drift,
    generalized_pi,
    jiles_atherton,
    prandtl_ishlinskii,
    preisach,
    stop_pi,
)
from torchhys.identification._family_spec import Fitter
from torchhys.identification._fit_cache import shared
from torchhys.operator import HysteresisOperator
from torchhys.registry import FAMILIES, make_operator

__all__ = ["OperatorSpec", "build_operators", "fit_data_dependent"]

OperatorSpec = str | Mapping[str, Any] | HysteresisOperator
"""``"eiho"``, ``{"name": NAME, **kwargs}``, ``{"fit": FAMILY, **options}`` or an
operator."""

_FAMILY_MODULES = (prandtl_ishlinskii, generalized_pi, preisach, stop_pi, jiles_atherton, drift)
"""The modules of the built-in families, loaded here: each registers its families in
:data:`torchhys.registry.FAMILIES` beside their builders, before a spec is looked up (the
registry loads this module on its first read: :data:`torchhys.registry.BUILTIN_FAMILIES`)."""


def _build(spec: object, argument: str, operator_kwargs: Mapping[str, Any]
           ) -> tuple[nn.Module, Fitter | None]:
    """One spec's module and fitter (None: nothing to fit)."""
    if isinstance(spec, Mapping) and "fit" in spec:
        family = spec["fit"]
        if "name" in spec:
            raise ValueError(f"{argument}: a spec has either 'name' (a registered operator) "
                             f"or 'fit' (a model family), got both: {dict(spec)!r}")
        if not isinstance(family, str) or family not in FAMILIES:
            raise ValueError(f"{argument}: no model family is called {family!r}; families: "
                             f"{sorted(FAMILIES)}")
        module, fitter = FAMILIES[family](spec)
        return module, None if fitter is None else shared(spec, fitter)
    if isinstance(spec, Mapping) and "name" not in spec:
        raise ValueError(f"{argument}: a spec dict needs a 'name' (a registered operator) or "
                         f"a 'fit' (a model family: {sorted(FAMILIES)}), got {dict(spec)!r}")
    try:
        return make_operator(spec, argument=argument,
                             **operator_kwargs if isinstance(spec, str) else {}), None
    except (ValueError, TypeError) as err:
        name = spec if isinstance(spec, str) else (
            spec.get("name") if isinstance(spec, Mapping) else None)
        if isinstance(name, str) and name in FAMILIES:
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
