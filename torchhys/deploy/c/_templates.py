"""One small C template per aten operation, for :mod:`torchhys.deploy.c`.

:data:`TEMPLATES` maps an op overload (``torch.ops.aten.addmm.default``) to an emitter
``emit(w, spec, *args, **kwargs)``: ``w`` is the :class:`~torchhys.deploy.c._writer.Writer`,
``spec`` the node's output (a :class:`~torchhys.deploy.c._writer.CTensor` of its dtype and shape,
or a list of them), the arguments are the node's, tensors as
:class:`~torchhys.deploy.c._writer.CTensor`. It writes C and returns the output's CTensor(s).
The templates, one concept a file: pointwise (:mod:`torchhys.deploy.c._pointwise`), views and
joins (:mod:`torchhys.deploy.c._views`), reductions and matrix products
(:mod:`torchhys.deploy.c._products`), normalisation and softmax
(:mod:`torchhys.deploy.c._norms`), sorting and indexing (:mod:`torchhys.deploy.c._indexing`).
"""

from __future__ import annotations

import operator
from typing import Any

import torch

from torchhys.deploy.c._indexing import INDEXING
from torchhys.deploy.c._norms import NORMS
from torchhys.deploy.c._pointwise import POINTWISE
from torchhys.deploy.c._products import PRODUCTS
from torchhys.deploy.c._views import JOINS, VIEWS, Emitter, _identity

OTHERS: dict[str, Emitter] = {**JOINS, **PRODUCTS, **NORMS, **INDEXING}


def _resolve(table: dict[str, Emitter]) -> dict[Any, Emitter]:
    """Op overloads of the names that this torch has."""
    out: dict[Any, Emitter] = {}
    for name, emit in table.items():
        packet, overload = name.split(".")
        op = getattr(getattr(torch.ops.aten, packet, None), overload, None)
        if op is not None:
            out[op] = emit
    return out


#: the pointwise ops (their results may be deferred into the loop of their reader)
POINTWISE_OPS = frozenset(_resolve(POINTWISE))

#: the views (no code: a new shape, strides and offset over their operand's array)
VIEW_OPS = frozenset(_resolve(VIEWS))

#: the op templates: op overload -> emitter
TEMPLATES: dict[Any, Emitter] = {
    **_resolve(POINTWISE), **_resolve(VIEWS), **_resolve(OTHERS),
    operator.getitem: lambda w, spec, xs, i: xs[i],
}

#: ops whose result depends on their tensor arguments' shapes and dtypes only (computed when
#: the C is written, with zeros for those arguments); ``empty`` ones become zeros
SHAPE_ONLY = set(_resolve({n: _identity for n in (
    "zeros_like.default", "ones_like.default", "full_like.default", "empty_like.default",
    "new_zeros.default", "new_ones.default", "new_full.default", "new_empty.default",
    "zeros.default", "ones.default", "full.default", "empty.memory_format", "arange.default",
    "arange.start", "arange.start_step", "scalar_tensor.default", "fill.Scalar",
)}))
