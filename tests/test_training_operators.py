"""Operator specs of the training module: names and dicts, data-dependent fits, warm-up."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from _helpers import play_reference
from _training_helpers import trainer

from torchhys import EIHO, Backlash, PrandtlIshlinskii, ZhaoTanOperator
from torchhys.functional import NonCausalWarning, backlash
from torchhys.identification.fitting import fit_prandtl_ishlinskii, play_width_grid
from torchhys.identification.specs import build_operators
from torchhys.registry import FAMILIES, OPERATORS
from torchhys.training import HysteresisDataModule, InverseHysteresisModule

torch.set_num_threads(1)


def small_data(**kwargs) -> HysteresisDataModule:
    return HysteresisDataModule(t_end=2 * math.pi, **kwargs)


def test_names_and_dicts_build_the_same_operators() -> None:
    by_name, fit_a = build_operators(["eiho", "zhao_tan"], {"rule": "dominant"})
    by_dict, fit_b = build_operators([{"name": "eiho", "rule": "dominant"},
                                      {"name": "zhao_tan", "rule": "dominant"}])
    assert [type(m) for m in by_name] == [type(m) for m in by_dict] == [EIHO, ZhaoTanOperator]
    assert [m.rule for m in by_name] == [m.rule for m in by_dict] == ["dominant"] * 2
    assert fit_a == fit_b == {}
    assert build_operators(None) == ([], {})
    ops, fitters = build_operators({"fit": "pi_ls", "n_widths": 7})
    assert isinstance(ops[0], PrandtlIshlinskii) and ops[0].n_operators == 7
    assert list(fitters) == [0]
    ops, fitters = build_operators([{"fit": "plays", "widths": [0.1, 0.5]}, "eiho"])
    assert isinstance(ops[0], Backlash) and fitters == {}  # explicit widths: nothing to fit
    given = Backlash(torch.tensor([0.2]))
    ops, fitters = build_operators([given])
    assert ops == [given] and fitters == {}


def test_a_name_is_the_registered_operator_and_fit_the_family() -> None:
    """``{"name": "preisach"}`` builds the registered Preisach with its options, nothing
    fitted; ``{"fit": "preisach"}`` the family identified on the training data."""
    (op,), fitters = build_operators({"name": "preisach", "n": 5, "lo": -1.0, "hi": 1.0})
    assert type(op) is OPERATORS["preisach"] and fitters == {}
    _, fitters = build_operators({"fit": "preisach", "n": 5})
    assert list(fitters) == [0]
    builtin = {n for n, b in FAMILIES.items() if b.__module__.startswith("torchhys.")}
    assert builtin == {"plays", "pi_ls", "pi_nonneg", "gpi", "preisach", "stop_pi",
                       "jiles_atherton", "drift"}


NOT_REGISTERED = r"no operator is registered as '{}'; registered names: \[.*'eiho'"


@pytest.mark.parametrize("spec, error, match", [
    ("no_such_op", ValueError, r"^operator\[0\]: " + NOT_REGISTERED.format("no_such_op")),
    ({"name": "pi"}, ValueError, "^operator\\[0\\]: " + NOT_REGISTERED.format("pi")),
    ({"fit": "pi"}, ValueError,
     r"^operator\[0\]: no model family is called 'pi'; families: \[.*'pi_ls'.*'preisach'"),
    ({"n": 3}, ValueError, r"^operator\[0\]: a spec dict needs a 'name' .* or a 'fit' "
                           r"\(a model family: \[.*'pi_ls'"),
    ({"name": "eiho", "fit": "pi_ls"}, ValueError, "has either 'name' .* or 'fit' .* got both"),
    # a family's name as a registered name: the error says how to write the family
    ("pi_ls", ValueError,
     NOT_REGISTERED.format("pi_ls") + r".*is written \{fit: pi_ls, \.\.\.\}\)$"),
    ({"name": "stop_pi", "n_widths": 8}, ValueError,
     r"^operator\[0\] 'stop_pi': .*'n_widths'.*is written \{fit: stop_pi, \.\.\.\}\)$"),
    ({"fit": "plays", "m": 3}, ValueError, r"^fit 'plays': unknown option\(s\) \['m'\]"),
    ({"fit": "pi_ls", "n_widths": 0}, ValueError,
     "^fit 'pi_ls': n_widths must be an int >= 1, got 0"),
    ({"fit": "plays", "power": -1.0}, ValueError, "'plays': power must be a finite number > 0"),
    ({"fit": "plays", "span_fraction": 0}, ValueError, "span_fraction must be a finite number"),
    ({"fit": "plays", "learnable": "false"}, ValueError, "learnable must be true or false"),
    ({"fit": "pi_ls", "learnable": 1}, ValueError, "learnable must be true or false, got 1"),
    ({"fit": "pi_ls", "power": float("nan")}, ValueError, "'pi_ls': power must be a finite"),
    ({"fit": "pi_ls", "ridge": -1.0}, ValueError, "ridge must be a finite number >= 0"),
    ({"fit": "pi_ls", "ridge": "auto"}, ValueError, "ridge must be a finite number >= 0"),
    ({"fit": "pi_ls", "ridge": float("inf")}, ValueError, "ridge must be a finite number >= 0"),
    ({"fit": "stop_pi", "n_widths": 0}, ValueError, "^fit 'stop_pi': n_widths must be an int"),
    ({"name": "eiho", "b": 1}, ValueError, "^operator\\[0\\] 'eiho': .*'b'"),
    (3, TypeError, r"^operator\[0\] must be a registered operator name, .* got int 3$"),
])
def test_bad_specs(spec, error, match) -> None:
    with pytest.raises(error, match=match) as raised:
        build_operators([spec])
    assert "\n" not in str(raised.value)
    with pytest.raises(error, match=match):
        InverseHysteresisModule(operator=[spec])


def test_pi_ls_and_plays_are_fitted_on_the_training_split() -> None:
    torch.manual_seed(0)
    dm = small_data(split=[0.6, 0.2, 0.2])
    module = InverseHysteresisModule(
        operator=[{"fit": "pi_ls", "n_widths": 12}, {"fit": "plays", "n": 4, "power": 2.0,
                                                      "span_fraction": 0.5}],
        hidden=6, optimizer="cg")
    trainer(max_epochs=1).fit(module, dm)
    x, y = dm.train_tensors()
    pi, plays = module.net.operators
    expected = fit_prandtl_ishlinskii(x, y, play_width_grid(x, 12))
    torch.testing.assert_close(pi.get_widths(), expected.get_widths())
    torch.testing.assert_close(pi.weights, expected.weights, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(pi.linear_weight, expected.linear_weight, rtol=1e-9, atol=1e-9)
    span = x.max() - x.min()
    torch.testing.assert_close(plays.get_widths(),
                               0.5 * span * (torch.arange(1, 5, dtype=x.dtype) / 4) ** 2)
    assert pi.weights.dtype == torch.float64  # fitted in float64 under precision 64-true


def test_fitted_operators_live_in_the_checkpoint(tmp_path) -> None:
    torch.manual_seed(0)
    dm = small_data(split=[0.6, 0.2, 0.2])
    spec = [{"fit": "pi_ls", "n_widths": 10}, {"fit": "plays", "n": 3}]
    module = InverseHysteresisModule(operator=spec, hidden=6, optimizer="cg")
    t = trainer(max_epochs=2, enable_checkpointing=True, default_root_dir=tmp_path)
    t.fit(module, dm)
    path = tmp_path / "m.ckpt"
    t.save_checkpoint(path)
    loaded = InverseHysteresisModule.load_from_checkpoint(path)
    assert loaded.hparams.operator == spec
    for a, b in zip(module.net.state_dict().values(), loaded.net.state_dict().values(),
                    strict=True):
        assert torch.equal(a, b)
    x = dm.x.unsqueeze(0)
    torch.testing.assert_close(loaded(x), module(x), rtol=0, atol=0)


def numpy_ridge_fit(x: np.ndarray, y: np.ndarray, widths: np.ndarray, warmup: int,
                    ridge: float) -> np.ndarray:
    """``[w0, w_1..w_N]`` minimizing ``mean(r^2) + ridge |w_1..N|^2`` over the samples after
    ``warmup``; the plays (a plain float64 loop) start at zero at the first sample."""
    plays = play_reference(x, widths)
    design = np.concatenate([x[..., None], plays], axis=-1)[:, warmup:].reshape(-1, 1 + len(widths))
    target = y[:, warmup:].reshape(-1)
    if ridge > 0:  # ridge as extra rows: |D w - y|^2 / m + ridge |E w|^2
        m = design.shape[0]
        penalty = np.sqrt(ridge) * np.eye(1 + len(widths))[1:]
        design = np.vstack([design / np.sqrt(m), penalty])
        target = np.concatenate([target / np.sqrt(m), np.zeros(len(widths))])
    return np.linalg.lstsq(design, target, rcond=None)[0]


@pytest.mark.parametrize("warmup", [0, 1, 50])
@pytest.mark.parametrize("ridge", [0.0, 1e-3])
def test_least_squares_with_warmup_matches_numpy(warmup: int, ridge: float) -> None:
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(2, 300, generator=gen, dtype=torch.float64).cumsum(-1)
    noise = 0.05 * torch.randn(2, 300, generator=gen, dtype=torch.float64)
    y = 0.3 * x + backlash(x, torch.tensor([0.5, 2.0], dtype=torch.float64)).sum(-1) + noise
    widths = play_width_grid(x, 8, power=1.0)
    model = fit_prandtl_ishlinskii(x, y, widths, ridge=ridge, warmup=warmup)
    ref = numpy_ridge_fit(x.numpy(), y.numpy(), widths.numpy(), warmup, ridge)
    np.testing.assert_allclose(float(model.linear_weight), ref[0], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(model.weights.numpy(), ref[1:], rtol=1e-7, atol=1e-9)
    if warmup > 0:  # leaving samples out changes the fit: the warm-up is not ignored
        assert not np.allclose(numpy_ridge_fit(x.numpy(), y.numpy(), widths.numpy(), 0, ridge),
                               ref, rtol=1e-5, atol=0)


def test_the_training_loss_leaves_out_the_warmup() -> None:
    torch.manual_seed(0)
    dm = small_data(warmup=100)
    module = InverseHysteresisModule(operator=[{"fit": "pi_ls", "n_widths": 8}], hidden=6,
                                     optimizer="cg")
    t = trainer(max_epochs=2)
    t.fit(module, dm)
    x, y = dm.train_tensors()
    with torch.no_grad():
        pred = module(x)
    logged = float(t.callback_metrics["train_loss"])
    assert logged == pytest.approx(float(F.mse_loss(pred[:, 100:], y[:, 100:])), rel=1e-12)
    assert logged != pytest.approx(float(F.mse_loss(pred, y)), rel=1e-6)
    expected = fit_prandtl_ishlinskii(x, y, play_width_grid(x, 8), warmup=100)
    torch.testing.assert_close(module.net.operators[0].weights, expected.weights)


def test_bad_warmup() -> None:
    with pytest.raises(ValueError, match="warmup must be an int >= 0"):
        small_data(warmup=-1)
    with pytest.raises(ValueError, match=r"warmup=620 leaves 9 of the 629 training samples"):
        small_data(warmup=620).setup()


def test_segment_eiho_with_the_least_squares_pi() -> None:
    """The reproduction's eiho_pi_nn: the per-segment EIHO and the PI of h as inputs."""
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonCausalWarning)
        module = InverseHysteresisModule(
            operator=[{"name": "eiho_segment", "a_formula": "sqrt"},
                      {"fit": "pi_ls", "n_widths": 30}], hidden=16, optimizer="cg")
    dm = small_data()
    t = trainer(max_epochs=20)
    t.fit(module, dm)
    assert module.net.hidden.in_features == 3
    assert float(t.callback_metrics["train_loss"]) < 5e-3
