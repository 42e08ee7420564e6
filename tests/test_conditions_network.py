"""InverseHysteresisNet with operating conditions (``n_conditions``, ``condition_degree``) and
model selection over conditions (``select(conditions=..., cv="condition")``): the features
against numpy products of Legendre polynomials, the readout against numpy least squares,
the folds' rows, the choice, the compensator and the compiled C against the network."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import torchhys
from torchhys import InverseHysteresisNet
from torchhys.deploy.c import to_c
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.selection import select
from torchhys.selection.candidates import solve_readout
from torchhys.selection.folds import Batch, make_folds

sys.path.insert(0, str(Path(__file__).parent))
from _export_helpers import CC, NO_CC, run_driver  # noqa: E402
from test_conditions_export import DRIVER  # noqa: E402

DT = torch.float64
VALUES = (0.0, 1.0, 2.0, 3.0, 4.0)


def _plant(T: int = 500) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One row per condition: plays whose widths and gain grow with it."""
    t = torch.linspace(0, 12, T, dtype=DT)
    x = torch.stack([torch.sin(t + i) * (1 + 0.1 * i) for i in range(len(VALUES))])
    r = torch.linspace(0.0, 0.4, 5, dtype=DT)
    y = torch.stack([torchhys.Backlash(r * (1 + 0.3 * v))(x[i:i + 1])[0][0].sum(-1)
                     * (1 + 0.5 * v) for i, v in enumerate(VALUES)])
    c = torch.tensor(VALUES, dtype=DT).view(-1, 1, 1).expand(len(VALUES), T, 1).contiguous()
    return x, c, y


def _net(degree: int = 2, hidden: int = 1, activation: str = "identity") -> InverseHysteresisNet:
    ops = [torchhys.Backlash(torch.linspace(0.0, 0.5, 6, dtype=DT))]
    return InverseHysteresisNet(ops, hidden, activation=activation, n_conditions=1,
                                condition_degree=degree).to(DT)


def _fitted(degree: int = 2) -> tuple[InverseHysteresisNet, torch.Tensor, torch.Tensor,
                                      torch.Tensor]:
    x, c, y = _plant()
    net = _net(degree)
    net.fit_normalization(x, y, conditions=c)
    solve_readout(net, Batch(x, y, torch.ones_like(x, dtype=torch.bool), c))
    return net, x, c, y


def test_features_are_the_products_with_the_legendre_basis() -> None:
    x, c, y = _plant()
    net = _net(2)
    net.fit_normalization(x, y, conditions=c)
    got = net.features(x, conditions=c)[0].numpy()
    plays = torchhys.Backlash(torch.linspace(0.0, 0.5, 6, dtype=DT))(x)[0].numpy()
    phi = np.concatenate([np.ones_like(x.numpy())[..., None], x.numpy()[..., None], plays], -1)
    ct = 2 * (c[..., 0].numpy() - 0.0) / 4.0 - 1
    b = np.polynomial.legendre.legvander(ct, 2)  # (rows, time, 3)
    want = (phi[..., :, None] * b[..., None, :]).reshape(*x.shape, -1)[..., 1:]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)
    assert net.hidden.in_features == want.shape[-1]


def test_the_identity_readout_is_numpy_least_squares() -> None:
    net, x, c, y = _fitted(1)
    feats = net.features(x, conditions=c)[0].reshape(-1, net.hidden.in_features).numpy()
    a = np.concatenate([feats, np.ones((feats.shape[0], 1))], 1)
    coef, *_ = np.linalg.lstsq(a, y.reshape(-1).numpy(), rcond=None)
    np.testing.assert_allclose(net(x, conditions=c)[0].reshape(-1).detach().numpy(), a @ coef,
                               rtol=0, atol=1e-9)


def test_the_network_takes_the_conditions_gradients() -> None:
    net = _net(2, hidden=3, activation="tanh")
    x, c, y = _plant(60)
    net.fit_normalization(x, y, conditions=c)
    cs = (c[:1, :40] + 0.3 * torch.sin(x[:1, :40, None])).clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda b: net(x[:1, :40], conditions=b)[0], (cs,))
    # in x through the memoryless part (the plays' kinks are the operator's own tests')
    plain = InverseHysteresisNet(None, 3, activation="tanh", n_conditions=1,
                                 condition_degree=2).to(DT)
    plain.fit_normalization(x, y, conditions=c)
    xs = x[:1, :40].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: plain(a, conditions=b)[0], (xs, cs))


def test_leave_one_condition_out_holds_each_condition_out_once() -> None:
    x, c, y = _plant(100)
    mask = torch.ones_like(x, dtype=torch.bool)
    first = torch.zeros(len(VALUES), dtype=torch.long)
    folds = make_folds(x, y, first, mask, "condition", conditions=c)
    assert len(folds) == len(VALUES)
    for j, f in enumerate(folds):
        assert torch.equal(f.val.x, x[[j]]) and torch.equal(f.val.conditions, c[[j]])
        assert sorted({float(v) for v in f.train.conditions[..., 0].flatten()}) == [
            v for k, v in enumerate(VALUES) if k != j]
        assert f.fit.conditions.shape[:-1] == f.fit.x.shape
    rolling = make_folds(x, y, first, mask, "condition", "rolling", conditions=c)
    assert [f.train.x.shape[0] for f in rolling] == [1, 2, 3, 4]


def test_select_over_conditions_prefers_the_conditioned_network() -> None:
    x, c, y = _plant()
    pi = [{"fit": "pi_nonneg", "n_widths": 8}]
    res = select([{"operator": None}, {"operator": pi}, {"operator": pi, "condition_degree": 1}],
                 x, y, conditions=c, cv="condition", warmup=50)
    assert res.chosen.index == 2
    assert res.scores[2].val_mse < 0.2 * res.scores[1].val_mse
    # a candidate without condition_degree does not see the conditions
    plain = select([{"operator": pi}], x, y, cv="recording", warmup=50)
    again = select([{"operator": pi}], x, y, conditions=c, cv="recording", warmup=50)
    assert plain.scores[0].val_mse == again.scores[0].val_mse
    assert again.model.n_conditions == 0 and res.model.n_conditions == 1
    assert "leave-one-condition-out" in res.describe()


def test_the_compensator_of_the_conditioned_network_is_the_network() -> None:
    net, x, c, _ = _fitted(2)
    comp = StreamingCompensator(net, direction="none", input_margin=0.0)
    u = comp(x[2], c[2])
    assert float((u - net(x[2], conditions=c[2])[0]).detach().abs().max()) < 1e-12
    with pytest.raises(ValueError, match="condition"):
        comp.step(x[2, :1])


@pytest.mark.skipif(CC is None, reason=NO_CC)
def test_the_c_step_of_the_conditioned_network(tmp_path: Path) -> None:
    net, x, c, _ = _fitted(2)
    h, src = to_c(net, tmp_path, direction="none")
    assert "const torchhys_comp_real *conditions);" in h.read_text()
    xs, cs = x[1, :200].clone(), (c[1, :200, 0] + 1.7 * torch.sin(x[1, :200])).clone()
    out = run_driver(tmp_path, DRIVER, src, zip(xs, cs, strict=True))
    u_c = torch.tensor([float(v) for v in out[1:201]], dtype=DT)
    comp = StreamingCompensator(net, direction="none")
    u = torch.stack([comp.step(xs[k:k + 1], cs[k].view(1, 1)) for k in range(200)], 1)[0]
    assert float((u_c - u.detach()).abs().max()) <= 1e-12
    assert float(u.detach().std()) > 0.1


def test_bad_conditions_are_one_line_errors() -> None:
    x, c, y = _plant(50)
    net = _net()
    with pytest.raises(ValueError, match=r"conditions missing.*1 condition"):
        net.fit_normalization(x, y)
    with pytest.raises(ValueError, match=r"condition 0 is constant"):
        net.fit_normalization(x, y, conditions=torch.ones_like(c))
    with pytest.raises(ValueError, match=r"conditions must have shape"):
        net.fit_normalization(x, y, conditions=c[..., 0])
    with pytest.raises(ValueError, match="finite"):
        bad = c.clone()
        bad[0, 3, 0] = float("nan")
        net.fit_normalization(x, y, conditions=bad)
    with pytest.raises(ValueError, match="without conditions"):
        InverseHysteresisNet(None, 1).to(DT)(x, conditions=c)
    with pytest.raises(ValueError, match="condition_degree"):
        select([{"operator": None, "condition_degree": 0}], x, y, conditions=c, cv=2)
    with pytest.raises(ValueError, match=r"condition_degree=1.*has none"):
        select([{"operator": None, "condition_degree": 1}], x, y, cv=2)
    with pytest.raises(ValueError, match=r"at least 3 are"):
        select([{"operator": None}], x[:2], y[:2], conditions=c[:2], cv="condition",
               warn_coverage=False)
    with pytest.raises(ValueError, match=r"row 0 .* vary"):
        varying = c + torch.linspace(0, 0.1, 50, dtype=DT).view(1, -1, 1)
        select([{"operator": None}], x, y, conditions=varying, cv="condition")
    with pytest.raises(ValueError, match=r"has no conditions"):
        select([{"operator": None}], x, y, cv="condition")
    with pytest.raises(ValueError, match=r"conditions must have x's shape"):
        select([{"operator": None}], x, y, conditions=c[:, :10], cv=2)


def test_a_conditioned_operator_inside_the_network_learns_its_widths(tmp_path: Path) -> None:
    from torchhys.conditions import ConditionedBacklash
    from torchhys.selection.candidates import train_full_batch

    x, c, y = _plant(300)
    half = torch.linspace(0.0, 0.2, 5, dtype=DT)  # half-widths of the plant's plays at c=0

    def net_of() -> InverseHysteresisNet:
        op = ConditionedBacklash(half.clone(), 1, degree=1).to(DT)
        return InverseHysteresisNet([op], 1, activation="identity", n_conditions=1,
                                    condition_degree=1).to(DT)

    mask = torch.ones_like(x, dtype=torch.bool)
    spec = {"optimizer": "lbfgs", "lr": 1.0, "schedule": None,
            "optimizer_kwargs": {"max_iter": 50, "line_search_fn": "strong_wolfe"}}
    losses = {}
    for learn in (False, True):
        net = net_of()
        net.operators[0].theta.requires_grad_(learn)
        net.fit_normalization(x, y, conditions=c)
        solve_readout(net, Batch(x, y, mask, c))
        if learn:
            train_full_batch(net, spec, Batch(x, y, mask, c), epochs=10)
        with torch.no_grad():
            losses[learn] = float((net(x, conditions=c)[0] - y).square().mean())
    # the widths move with the condition: learning theta fits the plant far better
    assert losses[True] < 0.2 * losses[False]
    assert float(net.operators[0].theta.abs().max()) > 0.05
    comp = StreamingCompensator(net, direction="none", input_margin=0.0)
    with torch.no_grad():
        assert float((comp(x[3], c[3]) - net(x[3], conditions=c[3])[0]).abs().max()) < 1e-12
    if CC is not None:
        h, src = to_c(net, tmp_path, direction="none", input_margin=None)
        assert "const torchhys_comp_real *conditions);" in h.read_text()
