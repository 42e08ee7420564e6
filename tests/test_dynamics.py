"""Linear dynamics against scipy.signal (lfilter, dlsim) in float64; stable parametrizations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _dynamics_helpers import BACKENDS, signal, stable_denominator, use_backend

scipy_signal = pytest.importorskip("scipy.signal")

from torchhys.dynamics import StateSpace, TransferFunction  # noqa: E402
from torchhys.functional.linear_filter import (  # noqa: E402
    lfilter,
    linear_recurrence,
    state_space,
)
from torchhys.registry import OPERATORS, make_operator  # noqa: E402

FILTERS = {  # name: (b, a)
    "biquad": ([0.2, 0.3, -0.1], [1.0, -1.5, 0.7]),
    "a0 != 1": ([0.4, -0.2, 0.1, 0.3], 2.0 * stable_denominator([0.9, 0.6 + 0.5j])),
    "long b": ([0.5, 0.1, -0.3, 0.2, 0.05], [1.0, -0.5]),
    "all-pole": ([1.0], stable_denominator([0.95 + 0.2j, -0.7, 0.4])),
    "fir": ([0.25, 0.5, 0.25], [1.0]),
    "gain": ([0.7], [2.0]),
}


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name", list(FILTERS))
@pytest.mark.parametrize("with_zi", [False, True])
def test_lfilter_matches_scipy(backend, name, with_zi):
    b, a = (np.asarray(c, dtype=np.float64) for c in FILTERS[name])
    n = max(len(a), len(b)) - 1
    x = signal((3, 257), seed=1)
    zi = torch.randn(3, n, dtype=torch.float64) if with_zi else None
    with use_backend(backend):
        y, zf = lfilter(x, torch.from_numpy(b), torch.from_numpy(a), state=zi)
    kwargs = {"zi": zi.numpy()} if with_zi else {"zi": np.zeros((3, n))}
    y_ref, zf_ref = scipy_signal.lfilter(b, a, x.numpy(), **kwargs)
    assert y.shape == (3, 257) and zf.shape == (3, n)
    np.testing.assert_allclose(y.numpy(), y_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(zf.numpy(), zf_ref, rtol=0, atol=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("T", [1, 2, 3, 17])
def test_lfilter_short_sequences_and_batch_shapes(backend, T):
    b = np.array([0.3, -0.2, 0.5, 0.1])
    a = stable_denominator([0.8, 0.5 + 0.3j])
    x = signal((2, 3, T), seed=2)
    zi = torch.randn(3, dtype=torch.float64)  # (n,): the same for every row
    with use_backend(backend):
        y, zf = lfilter(x, torch.from_numpy(b), torch.from_numpy(a), state=zi)
        y1, zf1 = lfilter(x[0, 0], torch.from_numpy(b), torch.from_numpy(a), state=zi)
    y_ref, zf_ref = scipy_signal.lfilter(b, a, x.numpy(), zi=np.broadcast_to(zi, (2, 3, 3)))
    assert y.shape == (2, 3, T) and zf.shape == (2, 3, 3)
    np.testing.assert_allclose(y.numpy(), y_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(zf.numpy(), zf_ref, rtol=0, atol=1e-12)
    tol = 0 if backend == "kernel" else 1e-13  # the scan's products depend on the batch
    torch.testing.assert_close(y1, y[0, 0], rtol=0, atol=tol)
    torch.testing.assert_close(zf1, zf[0, 0], rtol=0, atol=tol)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("splits", [[1] * 12, [5, 100, 152], [256, 1], [2, 255]])
def test_lfilter_chunked_equals_one_call(backend, splits):
    b, a = (torch.tensor(c, dtype=torch.float64) for c in FILTERS["a0 != 1"])
    x = signal((3, sum(splits)), seed=3)
    with use_backend(backend):
        whole, final = lfilter(x, b, a)
        parts, z = [], None
        for chunk in x.split(splits, dim=1):
            y, z = lfilter(chunk, b, a, state=z)
            parts.append(y)
    tol = 0 if backend == "kernel" else 1e-12  # the kernel runs the same arithmetic
    torch.testing.assert_close(torch.cat(parts, 1), whole, rtol=0, atol=tol)
    torch.testing.assert_close(z, final, rtol=0, atol=tol)


@pytest.mark.parametrize("backend", BACKENDS)
def test_float32_follows_float64(backend):
    b, a = (torch.tensor(c, dtype=torch.float64) for c in FILTERS["biquad"])
    x = signal((2, 500), seed=4)
    with use_backend(backend):
        y64, _ = lfilter(x, b, a)
        y32, _ = lfilter(x.float(), b.float(), a.float())
    assert y32.dtype == torch.float32
    torch.testing.assert_close(y32.double(), y64, rtol=0, atol=1e-4)


@pytest.mark.parametrize("backend", BACKENDS)
def test_state_space_matches_dlsim(backend):
    g = torch.Generator().manual_seed(5)
    A = 0.4 * torch.randn(3, 3, generator=g, dtype=torch.float64)
    B, C, D = (torch.randn(*s, generator=g, dtype=torch.float64) for s in [(3,), (2, 3), (2,)])
    u = signal((300,), seed=6)
    s0 = torch.randn(3, dtype=torch.float64)
    with use_backend(backend):
        y, s = state_space(u, A, B, C, D, state=s0)
        w = signal((2, 40, 3), seed=7)
        states = linear_recurrence(A, w)
    _, y_ref, x_ref = scipy_signal.dlsim((A.numpy(), B.numpy()[:, None], C.numpy(),
                                          D.numpy()[:, None], 1.0), u.numpy(), x0=s0.numpy())
    np.testing.assert_allclose(y.numpy(), y_ref, rtol=0, atol=1e-10)
    ref = np.zeros((2, 3))
    for t in range(40):
        ref = ref @ A.numpy().T + w[:, t].numpy()
        np.testing.assert_allclose(states[:, t].numpy(), ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.numpy(), A.numpy() @ x_ref[-1] + B.numpy() * u[-1].item(),
                               rtol=0, atol=1e-10)


@pytest.mark.parametrize("name", ["biquad", "a0 != 1", "long b", "all-pole"])
def test_transfer_function_from_coefficients_matches_scipy(name):
    b, a = FILTERS[name]
    block = TransferFunction.from_coefficients(b, a)
    x = signal((2, 300), seed=8)
    y, zf = block(x)
    y_ref = scipy_signal.lfilter(b, a, x.numpy())
    np.testing.assert_allclose(y.detach().numpy(), y_ref, rtol=0, atol=1e-10)
    bn, an = (np.asarray(c) / a[0] for c in (b, a))
    b_got, a_got = (c.detach().numpy() for c in block.coefficients())
    np.testing.assert_allclose(a_got[: len(an)], an, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b_got[: len(bn)], bn, rtol=0, atol=1e-12)
    assert zf.shape == (2, block.order)


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5])
def test_transfer_function_poles_stay_inside_radius(order):
    torch.manual_seed(order)
    block = TransferFunction(order, max_pole_radius=0.95).double()
    for _ in range(20):
        with torch.no_grad():
            for p in (block.alpha, block.beta, block.gamma):
                p.copy_(4 * torch.randn_like(p))
        a = block.denominator().detach().numpy()
        assert a[0] == 1.0 and np.abs(np.roots(a)).max() < 0.95


def test_transfer_function_default_is_a_unit_dc_gain_low_pass():
    block = TransferFunction(3, feedthrough=False).double()  # initialised in float32
    b, a = (c.detach().numpy() for c in block.coefficients())
    assert b[0] == 0 and np.isclose(b.sum() / a.sum(), 1.0, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.abs(np.roots(a)), 0.5, atol=1e-6)
    y, _ = block(torch.ones(1, 200, dtype=torch.float64))
    assert y[0, 0] == 0 and abs(y[0, -1].item() - 1.0) < 1e-6


@pytest.mark.parametrize("contractive", [True, False])
def test_state_space_from_matrices_matches_dlsim(contractive):
    A = np.array([[0.5, 0.3], [-0.2, 0.4]]) if contractive else np.array([[0.9, 0.8], [0, 0.7]])
    B, C, D = np.array([1.0, 0.5]), np.array([[1.0, -1.0], [0.3, 0.2]]), np.array([0.3, 0.0])
    assert (np.linalg.norm(A, 2) < 1) == contractive
    block = StateSpace.from_matrices(A, B, C, D)
    u = signal((400,), seed=9)
    y, s = block(u)
    _, y_ref, _ = scipy_signal.dlsim((A, B[:, None], C, D[:, None], 1.0), u.numpy())
    assert y.shape == (400, 2) and s.shape == (2,) and block.n_outputs == 2
    np.testing.assert_allclose(y.detach().numpy(), y_ref, rtol=0, atol=1e-10)
    A_got = block.matrices()[0].detach().numpy()
    assert np.linalg.norm(A_got, 2) <= block.max_norm + 1e-12
    if contractive:
        np.testing.assert_allclose(A_got, A, rtol=0, atol=1e-14)


def test_state_space_norm_bound_for_any_weights():
    torch.manual_seed(1)
    block = StateSpace(4, 2, max_norm=0.9).double()
    for scale in (0.1, 1.0, 10.0):
        with torch.no_grad():
            block.W.copy_(scale * torch.randn(4, 4))
        A = block.matrices()[0]
        assert torch.linalg.matrix_norm(A, ord=2) <= 0.9 + 1e-12


def test_registered_by_name():
    assert OPERATORS["transfer_function"] is TransferFunction
    assert OPERATORS["state_space"] is StateSpace
    block = make_operator("transfer_function", order=3, feedthrough=False)
    assert isinstance(block, TransferFunction) and block.order == 3
    ss = make_operator("state_space", n_states=3, n_outputs=2)
    y, s = ss(torch.randn(2, 30))
    assert y.shape == (2, 30, 2) and s.shape == (2, 3)
