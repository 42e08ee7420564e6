"""The adaptive step's parts of the two files of :func:`torchhys.deploy.c.to_c` (an
:class:`~torchhys.deploy.adaptive.AdaptiveCompensator`, ``adapt="rls"`` or ``"nlms"``): the
state's member names, the header's use text, macros and prototypes, and the source's
``PREFIX_weights`` and counters. The step itself is the exported graph's, as the static one.

A NULL ``PREFIX_state *`` (or a NULL ``conditions`` or ``out``) is the caller's error: the
static step does not test it either; the adaptive functions ``assert`` it (``<assert.h>``:
compiled out with ``NDEBUG``)."""

from __future__ import annotations

import torch

from torchhys.deploy.c._writer import Writer
from torchhys.deploy.streaming import STATE_F, STATE_F64, STATE_I, STATE_STARTED

#: the desired path's members (torchhys.deploy.c._files.MEMBERS); the measured path's get "m_"
_PATH = {STATE_F: "F", STATE_I: "I64", STATE_STARTED: "started", STATE_F64: "F64"}

#: the adaptive members after the two paths, with what they hold
EXTRA = {"W": "weights - offline weights (normalized)",
         "P": "RLS: covariance - initial covariance (m x m, row-major)",
         "Z": "the last update's regressors (m) and clamped measured response",
         "A": "[updates applied, pairs skipped (not finite), updates refused (direction)]"}

#: the struct members declared with the real type's name
REAL_MEMBERS = frozenset({"F", "m_F", "W", "P", "Z"})


def members(comp: torch.nn.Module) -> list[str]:
    """The state's C member names, in the state's order."""
    k = int(comp.k)
    names = [_PATH[i] for i in range(k)] + ["m_" + _PATH[i] for i in range(k)]
    return names + (["W", "P"] if comp.rls else ["W"]) + ["Z", "A"]


def layout(comp: torch.nn.Module) -> list[str]:
    """The header's layout lines of the measured path and the adaptive members."""
    k, m = int(comp.k), int(comp.m)
    sizes = {"W": m, "P": m * m, "Z": m + 1, "A": 3}
    rows = [f" *   m_{_PATH[i]}  the measured path's {_PATH[i]} (the same layout on the "
            "measured response)" for i in range(k)]
    return rows + [f" *   {name}[0:{sizes[name]}]  {EXTRA[name]}"
                   for name in members(comp)[2 * k:]]


def signature(prefix: str, comp: torch.nn.Module) -> str:
    """``PREFIX_real PREFIX_step_adapt(...)`` (no ``;``)."""
    real = f"{prefix}_real"
    cond = f", const {real} *conditions" if comp.n_conditions else ""
    return (f"{real} {prefix}_step_adapt({prefix}_state *s, {real} desired{cond}, "
            f"{real} measured_prev, {real} applied_prev)")


def use_text(prefix: str, comp: torch.nn.Module) -> str:
    """The header comment's paragraph of the adaptive step."""
    method = "recursive least squares" if comp.rls else "normalized LMS"
    return (
        f"Adaptive ({method}, torchhys.deploy.adaptive.AdaptiveCompensator): "
        "measured_prev is the response the device gave at the last sample and applied_prev the "
        "command applied then (NAN for either: no pair, no update, counted as skipped). The "
        f"readout's {int(comp.m)} weights move from the offline fit toward the pairs "
        f"seen; {prefix}_weights writes them in the readout's units, {prefix}_init (and "
        "a fresh zeroed state) returns to the offline weights. A NULL state, conditions or "
        "out pointer is the caller's error: the adaptive functions assert it (compiled "
        "out with NDEBUG).")


def macros(prefix: str, comp: torch.nn.Module) -> list[str]:
    return [f"#define {prefix}_N_WEIGHTS {int(comp.m)}"]


def prototypes(prefix: str) -> list[str]:
    s = f"const {prefix}_state *s"
    return [f"void {prefix}_weights({s}, {prefix}_real *out);",
            f"int64_t {prefix}_updates_count({s});",
            f"int64_t {prefix}_skipped_count({s});",
            f"int64_t {prefix}_refused_count({s});"]


def functions(prefix: str, w: Writer, comp: torch.nn.Module) -> list[str]:
    """The source's ``PREFIX_weights`` and the three counters (constants: w0, inv_scale)."""
    real, dtype = f"{prefix}_real", comp.low.dtype

    def array(name: str, t: torch.Tensor) -> str:
        values = [w.literal(v, dtype) for v in t.reshape(-1).tolist()]
        rows = ",\n    ".join(", ".join(values[i:i + 4]) for i in range(0, len(values), 4))
        return f"static const {real} {prefix}_{name}[{len(values)}] = {{\n    {rows}\n}};"

    lines = [array("w0", comp.w0), array("inv_scale", comp.inv_scale), "",
             f"void {prefix}_weights(const {prefix}_state *s, {real} *out)", "{",
             "    assert(s != NULL && out != NULL);",
             f"    for (int i = 0; i < {prefix}_N_WEIGHTS; ++i)",
             f"        out[i] = ({prefix}_w0[i] + s->W[i]) * {prefix}_inv_scale[i];", "}", ""]
    for col, name in enumerate(("updates", "skipped", "refused")):
        lines += [f"int64_t {prefix}_{name}_count(const {prefix}_state *s)", "{",
                  "    assert(s != NULL);", f"    return s->A[{col}];", "}", ""]
    return lines
