"""The exported step's graph as CasADi ``SX`` expressions, node by node, as the C generator
walks it (:mod:`torchhys.deploy.c._graph`): a translation per aten operation
(:mod:`torchhys.deploy.casadi._ops`), the nodes whose tensors are all known (parameters,
buffers, shapes) computed by torch, the step's ``t - t`` tests of non-finite values written
as ``fabs(t) < inf`` (CasADi simplifies ``t - t`` to 0; a comparison of a sum of them is
found by the C generator's :func:`~torchhys.deploy.c._finite.finite_test`, any other
``t - t`` is ``if_else(fabs(t) < inf, 0, NaN)``), and every operation without a
translation named at once with the module and source line it came from."""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import torch
from torch import fx

from torchhys.deploy.c._finite import finite_test
from torchhys.deploy.c._graph import _live, _origin, known_tensors
from torchhys.deploy.c._templates import SHAPE_ONLY
from torchhys.deploy.casadi._ops import is_symbolic, translations, zeros_for
from torchhys.deploy.casadi._values import (
    Sym,
    Unsupported,
    as_array,
    casadi,
    finite,
    objects,
    select,
)


def _stand_in(spec: Any) -> Any:
    """Zeros of the node's shape in place of a missing translation's output, so that the
    walk goes on and names every missing operation at once."""
    ca = casadi()
    if isinstance(spec, torch.Tensor):
        n = spec.numel()
        return Sym(objects([ca.SX(0.0)] * n, tuple(spec.shape)), spec.dtype)
    if isinstance(spec, (list, tuple)):
        return [_stand_in(s) for s in spec]
    return None


def _finite_test(spec: Any, terms: list[Any], ne: bool) -> Any:
    """``(t1 - t1) + ... != 0`` (``ne``; resp. ``== 0``): some ``t`` not finite (resp. all
    finite), broadcast to ``spec``'s shape."""
    ca = casadi()
    if not is_symbolic(terms):
        ok = torch.ones(tuple(spec.shape), dtype=torch.bool)
        for t in terms:
            ok = ok & torch.isfinite(torch.as_tensor(t))
        return ~ok if ne else ok
    arrays = np.broadcast_arrays(*[np.asarray(as_array(t), dtype=object) for t in terms])
    out = []
    for p in np.ndindex(tuple(spec.shape)):
        fin = functools.reduce(ca.logic_and, [finite(a[p]) for a in arrays])
        out.append(ca.logic_not(fin) if ne else fin)
    return Sym(objects(out, tuple(spec.shape)), torch.bool)


_SUB = torch.ops.aten.sub.Tensor


def _self_difference(spec: Any, t: Sym) -> Sym:
    """``t - t`` (a test of non-finite values, summed or compared later): 0 where ``t`` is
    finite, NaN where not (CasADi would simplify it to 0)."""
    ca = casadi()
    return Sym(objects([select(finite(e), ca.SX(0.0), ca.SX(math.nan)) for e in t.a.flat],
                       tuple(spec.shape)), spec.dtype)


def translate(ep: torch.export.ExportedProgram, inputs: list[Sym], who: str = "to_casadi"
              ) -> list[Any]:
    """The graph's outputs as symbolic tensors, its user inputs being ``inputs`` (in
    order). Raises ValueError naming every aten operation without a translation and where
    it came from."""
    sig = ep.graph_signature
    known = known_tensors(ep)
    users = list(sig.user_inputs)
    finite_tests = {n: t for n in ep.graph.nodes if (t := finite_test(
        n, lambda p: known.get(p.name) if p.op == "placeholder" else None)) is not None}
    live = _live(ep.graph, finite_tests)
    table = translations()
    env: dict[fx.Node, Any] = {}
    missing: dict[str, str] = {}
    outs: list[Any] = []
    for node in ep.graph.nodes:
        if node not in live:
            continue
        if node.op == "placeholder":
            env[node] = known[node.name] if node.name in known else inputs[
                users.index(node.name)]
        elif node.op == "call_function":
            env[node] = _node(node, env, table, missing, finite_tests.get(node))
        elif node.op == "output":
            outs = [env[a] for a in node.args[0]]
    if missing:
        raise ValueError(f"{who}: no CasADi translation for " + "; ".join(
            f"{op} (from {where})" for op, where in missing.items())
            + " (translations: torchhys.deploy.casadi._ops.translations())")
    return outs


def _node(node: fx.Node, env: dict, table: dict, missing: dict[str, str],
          finite: tuple[list[fx.Node], bool] | None) -> Any:
    spec = node.meta.get("val")
    if finite is not None:  # a t - t test: its operands are the t's
        return _finite_test(spec, [env[t] for t in finite[0]], finite[1])
    args, kwargs = fx.node.map_arg((node.args, node.kwargs), lambda n: env[n])
    if (node.target == _SUB and len(node.args) == 2 and node.args[0] is node.args[1]
            and not node.kwargs and isinstance(args[0], Sym)):
        return _self_difference(spec, args[0])
    if node.target in SHAPE_ONLY or not is_symbolic((args, kwargs)):
        a, k = zeros_for(args), zeros_for(kwargs)
        out = node.target(*a, **k)  # known operands: torch computes it
        if "empty" in str(node.target) and isinstance(out, torch.Tensor):
            out = torch.zeros_like(out)
        return out
    fn = table.get(node.target)
    if fn is None:
        missing.setdefault(str(node.target), _origin(node))
        return _stand_in(spec)
    try:
        out = fn(spec, *args, **kwargs)
    except Unsupported as e:
        missing.setdefault(f"{node.target} ({e})", _origin(node))
        return _stand_in(spec)
    if isinstance(spec, torch.Tensor) and (not isinstance(out, Sym)
                                           or out.shape != tuple(spec.shape)):
        raise RuntimeError(f"the CasADi translation of {node.target} gave "
                           f"{getattr(out, 'shape', type(out).__name__)}, torch "
                           f"{tuple(spec.shape)} (node {node.name})")
    return out

