"""Fitted model families shared between the runs of one process.

Model selection fits every candidate on every fold, and candidates share families: the
stop-type PI model with 40 thresholds is a candidate of its own and a part of two others in
``configs/measured.yaml``, fitted on the same fold's data each time. :func:`shared` wraps a
family's fitter so that a fit of the same spec on the same data (input, target, warm-up and
mask, compared by content; :func:`~torchhys.identification.generalized_pi.fit_key`: a ``gpi``
spec by the iterations it runs on them) is done once: later calls get a copy of the fitted
module, or the same :class:`~torchhys.identification.errors.FitError`. Only families whose fit
draws no random numbers are shared (:data:`SHARED_FAMILIES`), so a run's random state is the
same with the cache as without it. The last :data:`SIZE` fits are kept.
"""

from __future__ import annotations

import copy
import hashlib
import json
from collections import OrderedDict
from collections.abc import Callable, Mapping
from typing import Any

from torch import Tensor, nn

from torchhys.identification.errors import FitError
from torchhys.identification.generalized_pi import fit_key

SHARED_FAMILIES = frozenset({"plays", "pi_ls", "pi_nonneg", "gpi", "preisach", "stop_pi",
                             "drift"})
"""The families whose fit is a function of the spec and the data alone (``jiles_atherton``
draws random starts)."""
SIZE = 16
"""Fits kept (the least recently used is dropped)."""

_FITS: OrderedDict[tuple, nn.Module | FitError] = OrderedDict()

Fitter = Callable[[Tensor, Tensor, int, Tensor | None], nn.Module]


def clear() -> None:
    """Drop every kept fit."""
    _FITS.clear()


def _fingerprint(t: Tensor | None) -> tuple | None:
    if t is None:
        return None
    data = t.detach().cpu().contiguous()
    digest = hashlib.blake2b(data.numpy().tobytes(), digest_size=16).hexdigest()
    return (tuple(data.shape), str(data.dtype), digest)


def shared(spec: Mapping[str, Any], fit: Fitter) -> Fitter:
    """``fit`` (the fitter of the family ``spec["fit"]``), done once per spec and data in
    this process; ``fit`` itself for a family outside :data:`SHARED_FAMILIES` or a spec
    that is not plain data."""
    if spec.get("fit") not in SHARED_FAMILIES:
        return fit
    try:
        json.dumps(dict(spec), sort_keys=True, allow_nan=True)
    except (TypeError, ValueError):
        return fit

    def cached(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        try:  # the spec as it determines the fit on these data
            name = json.dumps(fit_key(spec, x, warmup, mask), sort_keys=True, allow_nan=True)
        except (TypeError, ValueError):  # what the fit itself refuses: not shared
            return fit(x, y, warmup, mask)
        key = (name, int(warmup), str(x.device), _fingerprint(x), _fingerprint(y),
               _fingerprint(mask))
        kept = _FITS.get(key)
        if kept is None:
            try:
                kept = copy.deepcopy(fit(x, y, warmup, mask))
            except FitError as err:
                kept = err
            _FITS[key] = kept
            while len(_FITS) > SIZE:
                _FITS.popitem(last=False)
        _FITS.move_to_end(key)
        if isinstance(kept, FitError):
            raise FitError(str(kept))
        return copy.deepcopy(kept)

    return cached
