"""MIMO linear dynamics: StateSpace(n_inputs=m) against scipy.signal.dlsim, TransferFunctionMatrix
against sums of scipy.signal.lfilter, lfilter with several filters, gradcheck, chunked == whole,
step == sequence (eager, TorchScript, torch.export), batches, bad input, one-input blocks in
the operator protocol (a one-input matrix inside a network: tests/test_conformance.py)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from _dynamics_helpers import BACKENDS, signal, stable_denominator, use_backend
from _helpers import run_split
from torch.autograd import gradcheck, gradgradcheck
from torch.func import functional_call

scipy_signal = pytest.importorskip("scipy.signal")

from torchhys import InverseHysteresisNet  # noqa: E402
from torchhys.dynamics import (  # noqa: E402
    StateSpace,
    TransferFunction,
    TransferFunctionMatrix,
)
from torchhys.functional.linear_filter import lfilter, state_space, state_space_step  # noqa: E402
from torchhys.operator import check_operator  # noqa: E402
from torchhys.operators.cascade import Cascade  # noqa: E402
from torchhys.registry import make_operator  # noqa: E402

# a 3 x 2 matrix: mixed orders (common order 2), a[0] != 1, a pure delay, a static gain
ENTRIES = [
    [([0.3, 0.1], [1.0, -0.5]), ([1.0, 0.2, 0.1], stable_denominator([0.6 + 0.5j]))],
    [([0.5], 2.0 * stable_denominator([-0.4, 0.7])), ([0.0, 1.0], [1.0, -0.9])],
    [([0.7], [1.0]), ([0.1, 0.2], stable_denominator([0.2 + 0.3j]))],
]


def _state_space(n: int = 3, p: int = 2, m: int = 3, seed: int = 0) -> StateSpace:
    torch.manual_seed(seed)
    return StateSpace(n, p, n_inputs=m).double()


def _inputs(shape: tuple[int, ...], seed: int = 0) -> torch.Tensor:
    """A float64 signal (..., time, m): independent random walks per input column."""
    return signal(shape[:-2] + (shape[-1], shape[-2]), seed=seed).transpose(-1, -2)


def _script(step: torch.nn.Module) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():  # torch.jit.script is deprecated in torch 2.13
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.script(step)


def _step_loop(step, x: torch.Tensor, state: list[torch.Tensor]):
    """A MIMO step run over x (batch, time, m): ((batch, time, p), state)."""
    outs = []
    for xt in x.unbind(1):
        f, state = step(xt, state)
        outs.append(f)
    return torch.stack(outs, 1), state


# --- against scipy ----------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("with_s0", [False, True])
def test_state_space_matches_dlsim(backend, with_s0):
    block = _state_space(n=3, p=2, m=3)
    x = _inputs((2, 60, 3), seed=1)
    s0 = torch.randn(2, 3, dtype=torch.float64) if with_s0 else None
    with use_backend(backend), torch.no_grad():
        y, final = block(x, s0)
    A, B, C, D = (t.detach().numpy() for t in block.matrices())
    assert B.shape == (3, 3) and D.shape == (2, 3) and y.shape == (2, 60, 2)
    for r in range(2):
        start = np.zeros(3) if s0 is None else s0[r].numpy()
        _, y_ref, s_ref = scipy_signal.dlsim((A, B, C, D, 1.0), x[r].numpy(), x0=start)
        np.testing.assert_allclose(y[r].numpy(), y_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(final[r].numpy(), A @ s_ref[-1] + B @ x[r, -1].numpy(),
                                   rtol=0, atol=1e-12)


def test_functional_state_space_batch_shapes():
    g = torch.Generator().manual_seed(3)
    A = 0.5 * torch.randn(4, 4, generator=g, dtype=torch.float64) / 2
    B, C, D = (torch.randn(*s, generator=g, dtype=torch.float64) for s in [(4, 2), (3, 4), (3, 2)])
    u = _inputs((2, 3, 25, 2), seed=3)
    s0 = torch.randn(4, generator=g, dtype=torch.float64)
    y, s = state_space(u, A, B, C, D, state=s0)
    assert y.shape == (2, 3, 25, 3) and s.shape == (2, 3, 4)
    _, y_ref, s_ref = scipy_signal.dlsim((A.numpy(), B.numpy(), C.numpy(), D.numpy(), 1.0),
                                         u[1, 2].numpy(), x0=s0.numpy())
    np.testing.assert_allclose(y[1, 2].numpy(), y_ref, rtol=0, atol=1e-12)
    # the step with the same matrices, sample by sample
    state, outs = s0.expand(6, 4), []
    for ut in u.reshape(6, 25, 2).unbind(1):
        yt, state = state_space_step(ut, state, A, B, C, D)
        outs.append(yt)
    torch.testing.assert_close(torch.stack(outs, 1), y.reshape(6, 25, 3), rtol=0, atol=1e-13)
    torch.testing.assert_close(state, s.reshape(6, 4), rtol=0, atol=1e-13)


def _scipy_matrix(block: TransferFunctionMatrix, x: np.ndarray, zi: np.ndarray | None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """y_i = sum_j lfilter(b_ij, a_ij, x_j) with the block's coefficients: (batch, time, p)
    and the delays (batch, p, m, order)."""
    b, a = (c.detach().numpy() for c in block.coefficients())
    p, m, n1 = b.shape
    ys, zs = np.zeros(x.shape[:2] + (p,)), np.zeros((x.shape[0], p, m, n1 - 1))
    for i in range(p):
        for j in range(m):
            z0 = np.zeros((x.shape[0], n1 - 1)) if zi is None else zi[:, i, j]
            y_ij, zs[:, i, j] = scipy_signal.lfilter(b[i, j], a[i, j], x[..., j], zi=z0)
            ys[..., i] += y_ij
    return ys, zs


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("with_zi", [False, True])
def test_transfer_function_matrix_matches_lfilter_sums(backend, with_zi):
    block = TransferFunctionMatrix.from_coefficients(ENTRIES)
    assert (block.order, block.n_outputs, block.n_inputs) == (2, 3, 2)
    x = _inputs((2, 80, 2), seed=2)
    zi = torch.randn(2, 3, 2, 2, dtype=torch.float64) if with_zi else None
    with use_backend(backend), torch.no_grad():
        y, zf = block(x, zi)
    y_ref, zf_ref = _scipy_matrix(block, x.numpy(), None if zi is None else zi.numpy())
    assert y.shape == (2, 80, 3) and zf.shape == (2, 3, 2, 2)
    np.testing.assert_allclose(y.numpy(), y_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(zf.numpy(), zf_ref, rtol=0, atol=1e-12)


def test_from_coefficients_keeps_each_entry():
    block = TransferFunctionMatrix.from_coefficients(ENTRIES)
    b, a = (c.detach().numpy() for c in block.coefficients())
    for i, row in enumerate(ENTRIES):
        for j, (bij, aij) in enumerate(row):
            bij, aij = np.asarray(bij, dtype=float), np.asarray(aij, dtype=float)
            np.testing.assert_allclose(b[i, j], np.pad(bij, (0, 3 - len(bij))) / aij[0],
                                       rtol=0, atol=1e-13)
            np.testing.assert_allclose(a[i, j], np.pad(aij, (0, 3 - len(aij))) / aij[0],
                                       rtol=0, atol=1e-13)
    assert block.alpha.dtype == torch.float64


def test_entries_start_as_the_siso_block():
    tf = TransferFunction(3)
    block = TransferFunctionMatrix(3, 2, 4)
    assert block.alpha.shape == (4, 2, 1) and block.numerator.shape == (4, 2, 4)
    b, a = block.coefficients()
    b1, a1 = tf.coefficients()
    torch.testing.assert_close(b, b1.expand(4, 2, 4), rtol=0, atol=0)
    torch.testing.assert_close(a, a1.expand(4, 2, 4), rtol=0, atol=0)
    x = signal((3, 40), seed=4).float()
    with torch.no_grad():
        y, _ = TransferFunctionMatrix(3)(x)
        y1, _ = tf(x)
    torch.testing.assert_close(y[..., 0], y1, rtol=0, atol=0)


def test_the_siso_block_is_the_1x1_case_without_entry_axes():
    """TransferFunction is a TransferFunctionMatrix whose parameters drop the (1, 1) entry
    axes: the same values, of a SISO filter's shapes (its saved state dicts)."""
    tf, block = TransferFunction(3, feedthrough=False), TransferFunctionMatrix(3, feedthrough=False)
    assert isinstance(tf, TransferFunctionMatrix) and (tf.n_inputs, tf.n_outputs) == (1, 1)
    siso, mimo = tf.state_dict(), block.state_dict()
    assert list(siso) == list(mimo) == ["alpha", "beta", "gamma", "numerator", "numerator_mask"]
    for key in ("alpha", "beta", "gamma", "numerator"):
        assert mimo[key].shape == (1, 1, *siso[key].shape)
        torch.testing.assert_close(mimo[key][0, 0], siso[key], rtol=0, atol=0)
    assert siso["numerator"].shape == (4,) and tf.coefficients()[1].shape == (4,)


@pytest.mark.parametrize("backend", BACKENDS)
def test_lfilter_with_one_filter_a_row(backend):
    b = torch.tensor([[0.2, 0.3, -0.1], [1.0, 0.0, 0.0], [0.5, 0.5, 0.0]], dtype=torch.float64)
    a = torch.tensor(np.stack([stable_denominator([0.7 + 0.4j]), [2.0, -1.0, 0.0],
                               stable_denominator([-0.5, 0.9])]), dtype=torch.float64)
    x = signal((2, 3, 50), seed=5)
    zi = torch.randn(2, 3, 2, dtype=torch.float64)
    with use_backend(backend):
        y, zf = lfilter(x, b, a, state=zi)
        y_shared, _ = lfilter(x, b[0], a, state=zi)  # a 1-D b is shared by the three filters
    for f in range(3):
        y_ref, zf_ref = scipy_signal.lfilter(b[f], a[f], x[:, f].numpy(), zi=zi[:, f].numpy())
        np.testing.assert_allclose(y[:, f].numpy(), y_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(zf[:, f].numpy(), zf_ref, rtol=0, atol=1e-12)
        y_ref = scipy_signal.lfilter(b[0], a[f], x[:, f].numpy(), zi=zi[:, f].numpy())[0]
        np.testing.assert_allclose(y_shared[:, f].numpy(), y_ref, rtol=0, atol=1e-12)


# --- gradients --------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
def test_lfilter_filters_gradcheck(backend):
    g = torch.Generator().manual_seed(6)
    x = torch.randn(2, 3, 12, generator=g, dtype=torch.float64)
    b = torch.randn(3, 3, generator=g, dtype=torch.float64)
    a = torch.tensor(np.stack([1.5 * stable_denominator([0.6 + 0.3j]),
                               stable_denominator([0.5, -0.8]),
                               stable_denominator([-0.2 + 0.7j])]), dtype=torch.float64)
    zi = torch.randn(2, 3, 2, generator=g, dtype=torch.float64)
    inputs = [t.requires_grad_() for t in (x, b, a, zi)]
    fn = lambda x, b, a, zi: lfilter(x, b, a, state=zi)  # noqa: E731
    with use_backend(backend):
        assert gradcheck(fn, inputs)
        assert gradgradcheck(fn, [t.detach()[..., :6].clone().requires_grad_()
                                  if t is x else t for t in inputs])


@pytest.mark.parametrize("backend", BACKENDS)
def test_state_space_gradcheck(backend):
    g = torch.Generator().manual_seed(7)
    u = torch.randn(2, 10, 2, generator=g, dtype=torch.float64)
    A = 0.3 * torch.randn(3, 3, generator=g, dtype=torch.float64)
    B, C, D = (torch.randn(*s, generator=g, dtype=torch.float64) for s in [(3, 2), (2, 3), (2, 2)])
    s0 = torch.randn(2, 3, generator=g, dtype=torch.float64)
    inputs = [t.requires_grad_() for t in (u, A, B, C, D, s0)]
    with use_backend(backend):
        assert gradcheck(lambda u, A, B, C, D, s0: state_space(u, A, B, C, D, state=s0), inputs)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("kind", ["tfm", "ss"])
def test_block_gradcheck_inputs_state_and_parameters(backend, kind):
    torch.manual_seed(8)
    if kind == "tfm":
        block = TransferFunctionMatrix(3, 2, 2).double()
        state = torch.randn(2, 2, 2, 3, dtype=torch.float64)
        with torch.no_grad():
            block.numerator.add_(0.3 * torch.randn_like(block.numerator))
            block.alpha.add_(0.2 * torch.randn_like(block.alpha))
    else:
        block = _state_space(n=2, p=2, m=2, seed=8)
        state = torch.randn(2, 2, dtype=torch.float64)
    names = [name for name, _ in block.named_parameters()]
    params = [p.detach().clone().requires_grad_() for p in block.parameters()]
    x = _inputs((2, 8, 2), seed=8).requires_grad_()
    state.requires_grad_()

    def fn(x, state, *values):
        y, s = functional_call(block, dict(zip(names, values, strict=True)), (x, state))
        return y, s

    with use_backend(backend):
        assert gradcheck(fn, [x, state, *params])


# --- streaming: chunks, steps, batches --------------------------------------------------------


def _blocks() -> dict[str, torch.nn.Module]:
    return {"tfm": TransferFunctionMatrix.from_coefficients(ENTRIES),
            "ss": _state_space(n=3, p=2, m=2, seed=9)}


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name", ["tfm", "ss"])
@pytest.mark.parametrize("splits", [[1] * 12, [5, 40, 75], [119, 1]])
def test_chunked_calls_equal_one_call(backend, name, splits):
    block = _blocks()[name]
    x = _inputs((3, sum(splits), 2), seed=10)
    with use_backend(backend), torch.no_grad():
        whole, final = block(x)
        chunked, state = run_split(block, x, splits)
    # the kernel runs the same arithmetic in the same order for the transfer functions
    tol = 0 if backend == "kernel" and name == "tfm" else 1e-12
    torch.testing.assert_close(chunked, whole, rtol=0, atol=tol)
    torch.testing.assert_close(state, final, rtol=0, atol=tol)


@pytest.mark.parametrize("name", ["tfm", "ss"])
def test_batch_rows_and_unbatched_input(name):
    block = _blocks()[name]
    x = _inputs((3, 50, 2), seed=11)
    with torch.no_grad():
        y, s = block(x)
        for r in range(3):
            y1, s1 = block(x[r])
            torch.testing.assert_close(y1, y[r], rtol=0, atol=1e-14)
            torch.testing.assert_close(s1, s[r], rtol=0, atol=1e-14)
        y2, _ = block(x[1:2], s[:1])  # a state without its batch dimension broadcasts
        y3, _ = block(x[1:2], s[0])
    torch.testing.assert_close(y2, y3, rtol=0, atol=0)
    assert y.shape == (3, 50, block.n_outputs)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name", ["tfm", "ss"])
def test_step_eager_and_scripted_equal_sequence(backend, name):
    block = _blocks()[name]
    x = _inputs((2, 70, 2), seed=12)
    with use_backend(backend), torch.no_grad():
        y, final = block(x)
    step = block.streaming_step(torch.float64)
    assert (step.n_inputs, step.n_outputs) == (2, block.n_outputs)
    for s in (step, _script(step)):
        f, state = _step_loop(s, x, step.initial_state(x[:, :1, 0]))
        torch.testing.assert_close(f, y, rtol=0, atol=1e-12)
        torch.testing.assert_close(state[0], final.reshape(2, -1), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["tfm", "ss"])
def test_exported_step_equals_sequence(name):
    block = _blocks()[name].float()
    x = _inputs((2, 30, 2), seed=13).float()
    step = block.streaming_step(torch.float32)
    state = step.initial_state(x[:, :1, 0])
    exported = torch.export.export(step, (x[:, 0], state)).module()
    with torch.no_grad():
        y, final = block(x)
        f, s = _step_loop(exported, x, state)
    torch.testing.assert_close(f, y, rtol=0, atol=1e-5)
    torch.testing.assert_close(s[0], final.reshape(2, -1), rtol=0, atol=1e-5)


# --- one input: the operator protocol as before -----------------------------------------------


def test_one_input_state_space_keeps_its_shapes():
    block = StateSpace(3, 2)
    assert block.n_inputs == 1
    shapes = {k: tuple(v.shape) for k, v in block.state_dict().items()}
    assert shapes == {"W": (3, 3), "B": (3,), "C": (2, 3), "D": (2,)}
    ss = StateSpace.from_matrices([[0.5, 0.1], [0.0, 0.3]], [[1.0], [0.5]], [[1.0, 0.0]],
                                  [[0.2]])
    assert ss.n_inputs == 1 and ss.B.shape == (2,) and ss.D.shape == (1,)
    mimo = StateSpace.from_matrices([[0.5, 0.1], [0.0, 0.3]], [[1.0, 0.0, 2.0], [0.5, 1.0, 0.0]],
                                    [[1.0, 0.0]])
    assert mimo.n_inputs == 3 and mimo.B.shape == (2, 3) and mimo.D.shape == (1, 3)
    assert not mimo.D.any()


@pytest.mark.parametrize("make", [
    lambda: StateSpace(2, 1, n_inputs=2),
    lambda: TransferFunctionMatrix(2, 3, 1),
])
def test_multi_input_block_is_not_an_operator(make):
    block = make()
    with pytest.raises(TypeError, match="has n_inputs = [23]: an operator takes one input"):
        check_operator(block)
    with pytest.raises(TypeError, match="n_inputs = [23]"):
        InverseHysteresisNet(block, hidden=4)
    with pytest.raises(TypeError, match="n_inputs = [23]"):
        Cascade(block, TransferFunction(2))
    with pytest.raises(TypeError, match="operator 'state_space' StateSpace has n_inputs = 2"):
        make_operator("state_space", n_inputs=2)
    with pytest.raises(TypeError, match="TransferFunctionMatrix has n_inputs = 3"):
        make_operator("transfer_function_matrix", n_inputs=3)
    assert make_operator("transfer_function_matrix", order=3, n_outputs=2).n_outputs == 2


# --- bad input --------------------------------------------------------------------------------


def _nan(x: torch.Tensor, value: float = math.nan) -> torch.Tensor:
    x = x.clone()
    x[0, 3, 1] = value
    return x


X = _inputs((2, 10, 2), seed=15)


@pytest.mark.parametrize("name", ["tfm", "ss"])
@pytest.mark.parametrize("x,state,error,match", [
    (X[..., :1], None, ValueError,
     r"x must have shape \(time, n_inputs\) or \(batch, time, n_inputs\) with n_inputs = 2, "
     r"got shape \(2, 10, 1\)"),
    (X[0, :, 0], None, ValueError, r"n_inputs = 2, got shape \(10,\)"),
    (X[None], None, ValueError, r"n_inputs = 2, got shape \(1, 2, 10, 2\)"),
    (X[:, :0], None, ValueError, "x must hold at least one sample"),
    (_nan(X), None, ValueError, r"x must be finite.*\(0, 3, 1\)"),
    (_nan(X, math.inf), None, ValueError, "x must be finite"),
    (X.int(), None, TypeError, "x must have a floating-point dtype"),
    (X, "zeros", ValueError, r"state must have shape"),
    (X, [0.0], TypeError, "state must be a torch.Tensor or None"),
])
def test_forward_bad_input(name, x, state, error, match):
    block = _blocks()[name]
    if isinstance(state, str):
        state = torch.zeros(5, 1, dtype=torch.float64)
    with pytest.raises(error, match=match):
        block(x, state)


@pytest.mark.parametrize("name", ["tfm", "ss"])
def test_step_bad_width(name):
    step = _blocks()[name].streaming_step(torch.float64)
    state = step.initial_state(X[:, :1, 0])
    with pytest.raises(ValueError, match="n_inputs = 2, got 1 columns"):
        step(X[:, 0, :1], state)
    with pytest.raises(Exception, match="n_inputs = 2, got 1 columns"):
        _script(step)(X[:, 0, :1], state)


def test_state_space_construction_errors():
    with pytest.raises(ValueError, match="n_inputs must be an int >= 1"):
        StateSpace(2, 1, n_inputs=0)
    good = dict(A=[[0.5, 0.0], [0.0, 0.2]], B=[[1.0, 0.0], [0.0, 1.0]], C=[[1.0, 1.0]])
    with pytest.raises(ValueError, match=r"\(n, n\), \(n, m\), \(p, n\), \(p, m\) with m = 2"):
        StateSpace.from_matrices(**good, D=[0.5])
    with pytest.raises(ValueError, match=r"\(n, m\).*got \(2, 2\), \(3, 2\)"):
        StateSpace.from_matrices(**good | {"B": np.ones((3, 2))})
    with pytest.raises(ValueError, match="not stable: it has an eigenvalue of magnitude 1.2"):
        StateSpace.from_matrices(**good | {"A": [[1.2, 0.0], [0.0, 0.2]]})
    with pytest.raises(ValueError, match="D must be finite"):
        StateSpace.from_matrices(**good, D=[[0.0, math.nan]])


def test_functional_bad_input():
    A, B, C, D = torch.zeros(3, 3), torch.zeros(3, 2), torch.zeros(2, 3), torch.zeros(2, 2)
    u = torch.zeros(4, 10, 2)
    with pytest.raises(ValueError, match=r"u must have shape \(\.\.\., time, 2\) for B of shape "
                                         r"\(3, 2\) \(2 inputs\), got shape \(4, 10, 3\)"):
        state_space(torch.zeros(4, 10, 3), A, B, C, D)
    with pytest.raises(ValueError, match=r"u must have shape \(\.\.\., time, n\)"):
        state_space(torch.zeros(10), A, B, C, D)
    with pytest.raises(ValueError, match=r"D must have shape \(2, 2\)"):
        state_space(u, A, B, C, torch.zeros(2))
    with pytest.raises(ValueError, match="u must be finite"):
        state_space(torch.full((4, 10, 2), math.nan), A, B, C, D)
    x = torch.zeros(2, 3, 10)
    with pytest.raises(ValueError, match=r"b must have shape \(length,\) or \(filters, length\) "
                                         r".*filters = 3\), got shape \(2, 3\)"):
        lfilter(x, torch.ones(2, 3), torch.ones(3))
    with pytest.raises(ValueError, match=r"a\[0\] must be non-zero.*\[0.0, 1.0\]"):
        lfilter(x, torch.ones(3, 2), torch.tensor([[1.0, 0.5], [0.0, 1.0], [1.0, 0.0]]))


@pytest.mark.parametrize("change,kwargs,match", [
    ({(1, 0): ([0.5], [1.0, -2.5, 1.0])}, {},
     r"H\[1\]\[0\]: a is not stable: it has a pole of magnitude 2 "),
    ({(0, 1): ([1.0], [1.0, 0.0, 1.0])}, {}, r"H\[0\]\[1\]: a is not stable.*magnitude 1 "),
    ({(2, 1): ([1.0], [0.0, 1.0])}, {}, r"H\[2\]\[1\]: a\[0\] must be non-zero.*non-causal"),
    ({(0, 0): ([0.3, math.nan], [1.0, -0.5])}, {}, r"H\[0\]\[0\]: b must be finite"),
    ({}, {"feedthrough": False}, r"H\[0\]\[0\]: b\[0\] must be 0 without feedthrough"),
    ({}, {"max_pole_radius": 0.8}, "max_pole_radius must exceed the largest pole magnitude"),
])
def test_from_coefficients_errors(change, kwargs, match):
    entries = [list(row) for row in ENTRIES]
    for (i, j), pair in change.items():
        entries[i][j] = pair
    with pytest.raises(ValueError, match=match):
        TransferFunctionMatrix.from_coefficients(entries, **kwargs)


@pytest.mark.parametrize("coefficients,match", [
    ([ENTRIES[0], ENTRIES[1][:1]], "row 1 has 1 entries, row 0 has 2"),
    ([[([1.0], [1.0, -0.5], [0.0])]], r"entry \[0\]\[0\] is not a \(b, a\) pair"),
    ([], "p rows of m"),
    ([[]], "row 0 is not a non-empty sequence"),
    (np.ones((2, 2, 2)), "p rows of m"),
    ([[([1.0], [2.0])]], "order = .* must be >= 1"),
])
def test_from_coefficients_bad_layout(coefficients, match):
    with pytest.raises(ValueError, match=match):
        TransferFunctionMatrix.from_coefficients(coefficients)
