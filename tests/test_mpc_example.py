"""examples/mpc_casadi.py, small: receding-horizon MPC through the CasADi forward model of a
Prandtl-Ishlinskii plant (casadi.Opti, ipopt) solves every horizon and tracks the reference
far better than the uncompensated command (u = reference), as the model's exact inverse
(exported with to_casadi) does; the commands stay in their bounds."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

casadi = pytest.importorskip("casadi")

EXAMPLE = Path(__file__).parents[1] / "examples" / "mpc_casadi.py"


def _example() -> object:
    spec = importlib.util.spec_from_file_location("mpc_casadi", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.skipif(not casadi.has_nlpsol("ipopt"), reason="casadi without its ipopt plugin")
def test_mpc_solves_and_beats_the_uncompensated_command() -> None:
    out = _example().run(steps=40, horizon=20)
    assert out["failed"] == 0
    assert out["uncompensated"] > 0.05  # the hysteresis the MPC has to undo
    assert out["mpc"] < 1e-3 and out["mpc"] < 0.01 * out["uncompensated"]
    assert out["inverse"] < 1e-12  # the exact inverse of the known plant
    assert np.abs(out["u"]).max() <= 3.0 + 1e-8
