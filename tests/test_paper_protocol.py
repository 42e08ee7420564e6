"""The paper's simulation protocol: EIHO-NN beats Zhao-Tan's network, which beats a plain one."""

from __future__ import annotations

import warnings

import pytest
import torch

from torchhys import InverseHysteresisNet
from torchhys.functional import NonCausalWarning
from torchhys.identification.fitting import fit_full_batch
from torchhys.plants import paper_simulation

PAPER_EIHO_MSE = 1.737e-3


@pytest.fixture
def one_thread():
    """One intra-op thread: float64 full-batch training is then bit-for-bit repeatable."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def train(operator: str | None, kwargs: dict, adam: int, lbfgs: int) -> float:
    _, x, h = paper_simulation(dtype=torch.float64)
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonCausalWarning)
        net = InverseHysteresisNet(operator, 168, operator_kwargs=kwargs).double()
        return fit_full_batch(net, h, x, adam_epochs=adam, lbfgs_epochs=lbfgs).mse


def zhao_tan_kwargs() -> dict:
    return {"scale": float(paper_simulation(dtype=torch.float64).h.std()) / 5}


def test_ranking_on_a_small_budget(one_thread: None) -> None:
    # measured with one thread: eiho 6.17e-3, zhao_tan 3.10e-2, plain 0.281 (repeatable)
    eiho = train("eiho_segment", {}, 300, 200)
    zhao_tan = train("zhao_tan", zhao_tan_kwargs(), 300, 200)
    plain = train(None, {}, 100, 50)
    assert eiho < 7.5e-3
    assert zhao_tan > 3 * eiho
    assert plain > 5 * zhao_tan


@pytest.mark.slow
def test_paper_figure_reached(one_thread: None) -> None:
    eiho = train("eiho_segment", {}, 2000, 10000)
    assert eiho <= PAPER_EIHO_MSE
    assert eiho < train("zhao_tan", zhao_tan_kwargs(), 2000, 3000)
