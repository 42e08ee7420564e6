"""The paper's simulation protocol: EIHO-NN beats Zhao-Tan's network, which beats a plain one."""

from __future__ import annotations

import warnings

import pytest
import torch

from torchhys import InverseHysteresisNet
from torchhys.fitting import fit_full_batch
from torchhys.functional import NonCausalWarning
from torchhys.plants import paper_simulation

PAPER_EIHO_MSE = 1.737e-3


def train(operator: str | None, kwargs: dict, adam: int, lbfgs: int) -> float:
    torch.set_num_threads(1)
    _, x, h = paper_simulation(dtype=torch.float64)
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonCausalWarning)
        net = InverseHysteresisNet(operator, 168, operator_kwargs=kwargs).double()
        return fit_full_batch(net, h, x, adam_epochs=adam, lbfgs_epochs=lbfgs).mse


def zhao_tan_kwargs() -> dict:
    return {"scale": float(paper_simulation(dtype=torch.float64).h.std()) / 5}


def test_ranking_on_a_small_budget() -> None:
    eiho = train("eiho", {"a": "segment"}, 300, 200)
    zhao_tan = train("zhao_tan", zhao_tan_kwargs(), 300, 200)
    plain = train(None, {}, 100, 50)
    assert eiho < 1e-2
    assert eiho < zhao_tan < plain
    assert plain > 5 * zhao_tan


@pytest.mark.slow
def test_paper_figure_reached() -> None:
    eiho = train("eiho", {"a": "segment"}, 2000, 10000)  # about 2 min on one core
    assert eiho <= PAPER_EIHO_MSE
    assert eiho < train("zhao_tan", zhao_tan_kwargs(), 2000, 3000)
