"""Value checks where the values can be read (``torchhys._checks.concrete``): in eager mode
every data-dependent check raises its one-line error as before; while ``torch.compile`` or
``torch.export`` traces, under ``vmap`` and on meta and fake tensors the value checks are
skipped (no host sync, no graph break) and the shape and dtype checks still raise, naming
the argument; the compiled C kernels never see a tensor without concrete values."""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable

import pytest
import torch
import torch._dynamo
from torch._subclasses.fake_tensor import FakeTensorMode

from torchhys._checks import check_finite, check_nonnegative_weights, check_widths, concrete
from torchhys.functional import backlash, lfilter, preisach
from torchhys.functional._branch import check_a
from torchhys.functional._compile import servable
from torchhys.functional.drift import check_drift_state, check_scales
from torchhys.functional.prandtl_ishlinskii import prandtl_ishlinskii_inverse_parameters
from torchhys.functional.preisach import (
    _relay_chunks,
    _relays_in_one_chunk,
    check_relay_state,
    relay_update,
)
from torchhys.functional.preisach_inverse import check_preisach_invertible
from torchhys.functional.stop_pi import _scalar, check_invertible, check_thresholds
from torchhys.functional.turning_points import resolve_threshold
from torchhys.operators.eiho import EIHO
from torchhys.step import StateBlock, _check_step_state

F64 = torch.float64
preisach_module = importlib.import_module("torchhys.functional.preisach")  # the name is the
# function's in torchhys.functional
NAN = math.nan


def t(*values: float) -> torch.Tensor:
    return torch.tensor(values, dtype=F64)


X = torch.linspace(-1.0, 1.0, 12, dtype=F64).reshape(2, 6)
X_NAN = X.clone().index_put_((torch.tensor(1), torch.tensor(4)), torch.tensor(NAN, dtype=F64))

# (what, call, match): every data-dependent check that concrete() guards, with a bad value
EAGER_ERRORS: list[tuple[str, Callable[[], object], str]] = [
    ("finite x", lambda: backlash(X_NAN, t(0.2)), r"^x must be finite, but it holds NaN or inf "
     r"\(first at index \(1, 4\)\)$"),
    ("finite", lambda: check_finite(t(1.0, math.inf), "v"), r"^v must be finite"),
    ("widths >= 0", lambda: backlash(X, t(0.2, -0.1)), r"^widths must be non-negative, got "
     r"minimum -0.1$"),
    ("weights >= 0", lambda: check_nonnegative_weights(t(1.0, -2.0), "weights", ">= 0"),
     r"^weights must be finite and >= 0, got minimum -2"),
    ("drift scales", lambda: check_scales(t(1.0, 0.0)), r"^scales must be finite and positive"),
    ("drift state", lambda: check_drift_state(t(0.0, -1.0), X), r"^state: the accumulated "
     r"variation \(column 1\) must be >= 0, got -1$"),
    ("EIHO a > 0", lambda: check_a(t(-1.0), False, 2), r"^a must be positive, got minimum -1$"),
    ("lfilter finite x", lambda: lfilter(X_NAN, t(1.0), t(1.0, -0.5)), r"^x must be finite"),
    ("lfilter a[0]", lambda: lfilter(X, t(1.0), t(0.0, 1.0)), r"^a\[0\] must be non-zero"),
    ("Preisach alpha >= beta", lambda: preisach(X, t(1.0), t(0.1), t(0.3)),
     r"^alpha must be >= beta for every relay, got alpha\[0\]=0.1 < beta\[0\]=0.3$"),
    ("Preisach relays", lambda: check_relay_state(t(1.0, 0.5), X, 2, "state"),
     r"^state must hold relay values \+1 or -1 only$"),
    ("PI inverse", lambda: prandtl_ishlinskii_inverse_parameters(t(0.2), t(-1.0), 0.5),
     r"^the Prandtl-Ishlinskii model has no inverse"),
    ("stop thresholds", lambda: check_thresholds(t(0.5, 0.0)), r"^thresholds must be "
     r"positive, got minimum 0$"),
    ("stop scalar", lambda: _scalar(torch.tensor(NAN, dtype=F64), "linear_weight", X),
     r"^linear_weight must be a finite real number"),
    ("stop inverse", lambda: check_invertible(t(0.5, -0.5).reshape(1, 2),
                                              torch.tensor(1.0, dtype=F64)),
     r"^weights must be non-negative"),
    ("Preisach inverse", lambda: check_preisach_invertible(t(-1.0), torch.tensor(1.0)),
     r"^weights must be finite and non-negative"),
    ("threshold", lambda: resolve_threshold(torch.tensor(-1.0), X), r"^threshold must be "
     r"finite, >= 0"),
    ("step state", lambda: _check_step_state([t(NAN).reshape(1, 1)], [StateBlock("plays", 1)],
                                             1),
     r"^state\[0\] \(block 'plays'\) must be floating point and finite$"),
    ("EIHO auto threshold", lambda: EIHO(threshold="auto").to(F64)(X),
     r"^threshold='auto' is not calibrated yet"),
]


@pytest.mark.parametrize("call, match", [pytest.param(c, m, id=w) for w, c, m in EAGER_ERRORS])
def test_eager_value_errors_kept(call: Callable[[], object], match: str) -> None:
    """In eager mode on real tensors each value check raises as it did (one line, the
    argument named)."""
    with pytest.raises(ValueError, match=match):
        call()


def test_concrete_where() -> None:
    """Concrete on real tensors (also under torch.func.grad), not on meta or fake tensors,
    not under vmap, not while torch.compile traces; non-tensors are ignored."""
    x = torch.ones(3, dtype=F64)
    assert concrete(x) and concrete(1.0, x, None) and concrete()
    assert not concrete(x.to("meta")) and not concrete(x, x.to("meta"))
    assert not concrete(FakeTensorMode().from_tensor(x))
    seen: list[bool] = []
    torch.func.vmap(lambda v: (seen.append(concrete(v)), v)[1])(torch.ones(2, 3))
    torch.func.grad(lambda v: (seen.append(concrete(v)), v.sum())[1])(x)
    assert seen == [False, True]
    with pytest.raises(ValueError, match=r"^v must be finite"):  # grad reads values: checked
        torch.func.grad(lambda v: check_finite(v, "v").sum())(t(1.0, NAN))
    torch._dynamo.reset()
    traced = torch.compile(lambda v: v + 1 if concrete(v) else v - 1, fullgraph=True,
                           backend="eager")
    assert torch.equal(traced(x), x - 1)
    assert concrete(x)  # after a compiled call, eager again


def test_kernels_only_on_concrete_tensors() -> None:
    """The C kernels read a tensor's memory: a meta, fake or vmap-batched tensor is never
    servable (a fake tensor handed to the kernel read unallocated memory)."""
    x = torch.ones(2, 5, dtype=F64)
    assert servable(x)
    assert not servable(x.to("meta")) and not servable(FakeTensorMode().from_tensor(x))
    seen: list[bool] = []
    torch.func.vmap(lambda v: (seen.append(servable(v)), v)[1])(x)
    assert seen == [False]


def _all_checks(x: torch.Tensor) -> torch.Tensor:
    """Every guarded value check on good values, then a computation: what a traced forward
    runs through."""
    w = torch.full((2,), 0.3, dtype=x.dtype, device=x.device)
    check_finite(x, "x")
    check_widths(w)
    check_nonnegative_weights(w, "weights", ">= 0")
    check_scales(w)
    check_drift_state(torch.stack([x[:, 0], x[:, 0].abs()], 1), x)
    check_a(w, False, x.shape[0])
    check_relay_state(torch.ones_like(w), x, 2, "state")
    check_thresholds(w)
    check_invertible(w.reshape(2, 1), w[0])
    check_preisach_invertible(w, w[0])
    resolve_threshold(w[0], x)
    return backlash(x, w)


def test_traced_checks_no_graph_break() -> None:
    """Under torch.compile(fullgraph=True) the value checks make no graph break and no host
    sync; the output equals eager; a NaN passes through as a NaN (no check under tracing)
    and eager still raises on it afterwards."""
    ref = _all_checks(X)
    torch._dynamo.reset()
    explained = torch._dynamo.explain(_all_checks)(X)
    assert explained.graph_break_count == 0, explained.break_reasons
    compiled = torch.compile(_all_checks, fullgraph=True, backend="eager")
    torch.testing.assert_close(compiled(X), ref, rtol=0, atol=1e-14)
    assert compiled(X_NAN).shape == ref.shape  # not checked under tracing: no error
    with pytest.raises(ValueError, match=r"^x must be finite"):
        _all_checks(X_NAN)


@pytest.mark.parametrize("where", ["meta", "fake", "vmap"])
def test_checks_on_symbolic_tensors(where: str) -> None:
    """On meta and fake tensors and under vmap the checks pass without reading values and the
    output has eager's shape (the pure-torch paths run, no kernel)."""
    ref = _all_checks(X)
    if where == "meta":
        out = _all_checks(X.to("meta"))
        assert out.is_meta
    elif where == "fake":
        with FakeTensorMode() as mode:
            out = _all_checks(mode.from_tensor(X))
    else:
        out = torch.func.vmap(_all_checks)(torch.stack([X, -X, 0.5 * X]))[1]
        torch.testing.assert_close(out, _all_checks(-X), rtol=0, atol=1e-14)
    assert out.shape == ref.shape


def test_preisach_one_chunk_equals_chunks(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where values cannot be read the Preisach relays run as one chunk over every relay's
    own levels: the same states as the chunked path over the unique levels (repeated
    levels, ties with the input on the grid, several chunks)."""
    g = torch.Generator().manual_seed(1)
    x = ((torch.randn(3, 700, generator=g, dtype=F64).cumsum(1) * 0.1).clamp(-1, 1) * 4
         ).round() / 4
    levels = torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0], dtype=F64)
    i, j = torch.tril_indices(5, 5)
    alpha, beta = levels[i], levels[j]
    r0 = torch.where(torch.rand(3, alpha.shape[0], generator=g) < 0.5, 1.0, -1.0).to(F64)
    monkeypatch.setattr(preisach_module, "_CHUNK", 3 * 15 * 50)  # chunks of 50 samples
    chunks = list(_relay_chunks(x, alpha, beta, r0))
    assert len(chunks) == 14
    (start, stop, one), = _relays_in_one_chunk(x, alpha, beta, r0)
    assert (start, stop) == (0, x.shape[1])
    assert torch.equal(torch.cat([r for *_, r in chunks], -1), one)
    # and the loop of single steps, the streaming path
    r, steps = r0, []
    for k in range(x.shape[1]):
        r = relay_update(x[:, k:k + 1], alpha, beta, r)
        steps.append(r.t())
    assert torch.equal(torch.stack(steps, -1), one)


def test_preisach_traced_equals_eager() -> None:
    """The Preisach model on meta tensors has eager's shape, and under torch.compile
    (fullgraph) eager's output."""
    w = torch.rand(3, dtype=F64)
    alpha, beta = t(0.5, 0.0, 0.5), t(-0.5, 0.0, 0.5)
    ref = preisach(X, w, alpha, beta)
    meta = preisach(*(v.to("meta") for v in (X, w, alpha, beta)))
    assert meta.is_meta and meta.shape == ref.shape
    torch._dynamo.reset()
    compiled = torch.compile(lambda v: preisach(v, w, alpha, beta), fullgraph=True,
                             backend="eager")
    torch.testing.assert_close(compiled(X), ref, rtol=0, atol=0)


@pytest.mark.parametrize("where", ["compile", "export", "vmap", "meta"])
def test_shape_and_dtype_errors_under_tracing(where: str) -> None:
    """A shape or dtype error is still raised under tracing, naming the argument (under
    torch.compile(fullgraph=True) torch wraps it: its message holds the check's)."""
    w = t(0.2)
    bad = {"compile": torch.ones(2, 2, 2, dtype=F64), "export": torch.ones(2, 2, 2, dtype=F64),
           "vmap": torch.ones(3, 2, 2, 2, dtype=F64), "meta": torch.ones(2, 4, device="meta",
                                                                         dtype=torch.long)}[where]
    match = (r"x must have floating-point dtype|x must have a floating-point dtype"
             if where == "meta" else r"x must have shape \(time,\) or \(batch, time\), got shape "
             r"\(2, 2, 2\)")
    with pytest.raises((ValueError, TypeError, RuntimeError), match=match):
        if where == "compile":
            torch._dynamo.reset()
            torch.compile(lambda v: backlash(v, w), fullgraph=True, backend="eager")(bad)
        elif where == "export":
            class Play(torch.nn.Module):
                def forward(self, v: torch.Tensor) -> torch.Tensor:
                    return backlash(v, w)
            torch.export.export(Play(), (bad,))
        elif where == "vmap":
            torch.func.vmap(lambda v: backlash(v, w))(bad)
        else:
            backlash(bad, w.to("meta"))


@pytest.mark.parametrize("module, name", [
    ("torchhys.functional._branch", "eiho"), ("torchhys.functional._branch", "zhao_tan"),
    ("torchhys.functional.preisach", "preisach"),
    ("torchhys.functional.preisach_inverse", "preisach_inverse"),
])
def test_paths_without_readable_values_equal_eager(monkeypatch: pytest.MonkeyPatch,
                                                   module: str, name: str) -> None:
    """The paths taken where the values cannot be read (the branch stack through every
    sample, the relays in one chunk, the Preisach inverse's loop of steps over levels with
    their repeats), run on real tensors: eager's output (the windows of the inverse and its
    loop of steps round apart by an ulp)."""
    from torchhys._conformance import signal
    from torchhys.testing import example_of

    torch.manual_seed(0)
    op = example_of(name).build().to(F64)
    x = signal(300).requires_grad_()  # with a gradient: the pure-torch paths (no kernel)
    ref = op(x)[0]
    monkeypatch.setattr(importlib.import_module(module), "concrete", lambda *a: False)
    got = op(x)[0]
    torch.testing.assert_close(got, ref, rtol=0, atol=4 * torch.finfo(F64).eps)
    if name != "preisach_inverse":
        assert torch.equal(got, ref)


def test_jiles_atherton_reads_no_buffer_value() -> None:
    """Jiles-Atherton's substeps are a Python int, set or loaded (its saved buffer read
    then): a meta copy runs, a loaded state dict sets them."""
    from torchhys.operators.jiles_atherton import JilesAtherton

    op = JilesAtherton(substeps=3).to(F64)
    loaded = JilesAtherton().to(F64)
    loaded.load_state_dict(op.state_dict())
    assert loaded.substeps == 3 and int(loaded.saved_substeps) == 3
    torch.testing.assert_close(loaded(X)[0], op(X)[0], rtol=0, atol=0)
    meta = JilesAtherton(substeps=3).to("meta")
    assert meta(X.to("meta"))[0].shape == X.shape
