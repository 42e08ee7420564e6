"""Preisach: clear errors naming the argument, and the one warning about the input range."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from torchhys.functional.preisach import preisach, preisach_grid, relay_states
from torchhys.identification.preisach import fit_preisach, select_penalty
from torchhys.operators.preisach import Preisach

A, B = preisach_grid(-1.0, 1.0, 3)
X = torch.linspace(-1.0, 1.0, 20)


@pytest.mark.parametrize(
    "lo, hi, n, err, match",
    [
        (-1.0, 1.0, 0, ValueError, "n must be an int >= 1"),
        (-1.0, 1.0, 2.5, ValueError, "n must be an int >= 1"),
        (-1.0, 1.0, True, ValueError, "n must be an int >= 1"),
        (1.0, 1.0, 3, ValueError, "lo must be less than hi"),
        (2.0, 1.0, 3, ValueError, "lo must be less than hi"),
        (math.nan, 1.0, 3, ValueError, "lo must be finite"),
        (-1.0, math.inf, 3, ValueError, "hi must be finite"),
        ("0", 1.0, 3, TypeError, "lo must be a real number"),
    ],
)
def test_bad_grid(lo, hi, n, err, match):
    with pytest.raises(err, match=match):
        preisach_grid(lo, hi, n)
    with pytest.raises(err, match=match):
        Preisach(lo, hi, n)


@pytest.mark.parametrize(
    "kwargs, err, match",
    [
        ({"x": torch.tensor([0.0, math.nan])}, ValueError, "x must be finite"),
        ({"x": torch.zeros(2, 3, 4)}, ValueError, r"x must have shape \(time,\)"),
        ({"x": torch.zeros(2, 0)}, ValueError, "at least one sample"),
        ({"x": torch.arange(4)}, TypeError, "x must have a floating-point dtype"),
        ({"alpha": A[:2]}, ValueError, "alpha and beta must have the same shape"),
        ({"alpha": B, "beta": A}, ValueError, r"alpha must be >= beta .* alpha\[1\]"),
        ({"alpha": torch.zeros(0), "beta": torch.zeros(0)}, ValueError, "K >= 1"),
        ({"beta": torch.full((6,), math.nan)}, ValueError, "beta must be finite"),
        ({"state": torch.zeros(6)}, ValueError, "state must hold relay values"),
        ({"state": torch.ones(2, 6)}, ValueError, r"state must have shape \(6,\) or \(1, 6\)"),
        ({"smooth": 0.0}, ValueError, "smooth must be None or a finite number > 0"),
        ({"smooth": math.inf}, ValueError, "smooth must be None"),
    ],
)
def test_bad_relay_input(kwargs, err, match):
    args = {"x": X, "alpha": A, "beta": B, **kwargs}
    with pytest.raises(err, match=match):
        relay_states(args.pop("x"), args.pop("alpha"), args.pop("beta"), **args)


def test_bad_weights_and_module_options():
    with pytest.raises(ValueError, match=r"weights must have shape \(6,\)"):
        preisach(X, torch.ones(5), A, B)
    with pytest.raises(ValueError, match="weights must be finite"):
        preisach(X, torch.full((6,), math.nan), A, B)
    with pytest.raises(ValueError, match="initial must be one of"):
        Preisach(-1.0, 1.0, 3, initial="saturated")
    with pytest.raises(ValueError, match=r"initial must hold relay values \+-1, got values \[0"):
        Preisach(-1.0, 1.0, 3, initial=torch.zeros(6))
    with pytest.raises(ValueError, match=r"initial must be one of .* got shape \(3,\)"):
        Preisach(-1.0, 1.0, 3, initial=torch.ones(3))
    for flag in ("linear", "offset"):
        with pytest.raises(TypeError, match=f"{flag} must be True or False, got str 'no'"):
            Preisach(-1.0, 1.0, 3, **{flag: "no"})
    with pytest.raises(ValueError, match=r"x must hold at least one row, got shape \(0, 5\)"):
        Preisach(-1.0, 1.0, 3)(torch.zeros(0, 5))
    with pytest.raises(ValueError, match="smooth must be None"):
        Preisach(-1.0, 1.0, 3, smooth=-0.1)
    m = Preisach(-1.0, 1.0, 3)
    with pytest.raises(ValueError, match="^state must hold relay values"):  # forward's name
        m(X, torch.zeros(6))


def test_negative_weights_in_a_state_dict():
    m = Preisach(-1.0, 1.0, 3)
    sd = m.state_dict()
    sd["weights"] = torch.tensor([0.1, -0.2, 0.0, 0.3, 0.1, 0.1])
    with pytest.raises(ValueError, match=r"weights must be finite and >= 0, got \[-0\.2"):
        m.load_state_dict(sd)
    sd["weights"] = torch.full((6,), math.nan)
    with pytest.raises(ValueError, match="weights must be finite and >= 0"):
        m.load_state_dict(sd)
    outer = torch.nn.Sequential(Preisach(-1.0, 1.0, 3))
    with pytest.raises(ValueError, match=r"0\.weights must be"):
        outer.load_state_dict({f"0.{k}": v for k, v in sd.items()})
    sd["weights"] = torch.full((6,), 0.5)
    m.load_state_dict(sd)
    assert bool((m.weights == 0.5).all())


@pytest.mark.parametrize("key, value, match", [
    ("alpha", torch.full((6,), math.nan), "alpha must be finite"),
    ("beta", torch.full((6,), 5.0), "alpha >= beta"),
])  # initial relays of 0: tests/test_conformance.py
def test_bad_grid_or_relays_in_a_state_dict(key, value, match):
    m = Preisach(-1.0, 1.0, 3)
    before = {k: v.clone() for k, v in m.state_dict().items()}
    sd = {k: v.clone() for k, v in m.state_dict().items()}
    sd["weights"] = torch.full((6,), 0.5)
    sd[key] = value.to(sd[key].dtype)
    with pytest.raises(ValueError, match=match):
        m.load_state_dict(sd)
    assert all(torch.equal(v, before[k]) for k, v in m.state_dict().items())
    assert (m.lo, m.hi) == (-1.0, 1.0)


def test_a_rejected_state_dict_leaves_a_composite_unchanged():
    """Loading is all or nothing: the Preisach stage rejects its density after the PI stage
    before it would have loaded (nn.Module loads module by module)."""
    from torchhys import Cascade, InverseHysteresisNet, PrandtlIshlinskii

    def cascade(scale: float) -> Cascade:
        return Cascade([PrandtlIshlinskii(torch.tensor([0.2, 0.5]) * scale,
                                          torch.tensor([0.3, 0.1]) * scale),
                        Preisach(-1.0, 1.0, 3)])

    for module, other in ((cascade(1.0), cascade(2.0)),
                          (InverseHysteresisNet([cascade(1.0)], 2),
                           InverseHysteresisNet([cascade(2.0)], 2))):
        before = {k: v.clone() for k, v in module.state_dict().items()}
        sd = other.state_dict()
        key = next(k for k in sd if k.endswith("weights") and sd[k].numel() == 6)
        sd[key] = torch.full((6,), -1.0)
        with pytest.raises(ValueError, match="weights must be finite and >= 0"):
            module.load_state_dict(sd)
        same(module.state_dict(), before)
        with pytest.raises(RuntimeError, match="size mismatch"):
            module.load_state_dict({**other.state_dict(), key: torch.ones(7)})
        same(module.state_dict(), before)
        module.load_state_dict(other.state_dict())  # a valid one loads
        same(module.state_dict(), other.state_dict())


def same(a: dict, b: dict) -> None:
    """Equal state dicts (a network's unfitted normalization buffers are NaN)."""
    assert list(a) == list(b)
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, equal_nan=True, msg=k)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"x": torch.tensor([0.0, math.nan, 1.0])}, "x must be finite"),
        ({"y": torch.tensor([0.0, 1.0, math.nan])}, "y must be finite"),
        ({"y": torch.zeros(4)}, "x and y must have the same shape"),
        ({"warmup": 3}, r"warmup must leave samples to fit: warmup=3 of 3 samples"),
        ({"warmup": 30}, "warmup must leave samples to fit: warmup=30 of 3 samples"),
        ({"warmup": -1}, "warmup must be an int >= 0, got -1"),
        ({"warmup": 1.0}, "warmup must be an int >= 0, got 1.0"),
        ({"ridge": -1.0}, "ridge must be >= 0"),
        ({"smoothness": math.nan}, "smoothness must be finite"),
        ({"x": torch.ones(3)}, r"x is constant \(1\): its range gives no grid"),
        ({"x": torch.ones(3), "lo": 1.0, "hi": 1.0}, "lo must be less than hi"),
        ({"n": 0}, "n must be an int >= 1"),
    ],
)
def test_bad_fit_input(kwargs, match):
    args = {"x": torch.tensor([0.0, 1.0, -1.0]), "y": torch.zeros(3), **kwargs}
    with pytest.raises(ValueError, match=match):
        fit_preisach(args.pop("x"), args.pop("y"), **args)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"penalties": []}, "penalties must hold at least one value"),
        ({"penalties": [0.1, -1.0]}, "penalties must be >= 0"),
        ({"kind": "lasso"}, r"kind must be one of \('ridge', 'smoothness'\)"),
        ({"validation": 1.0}, r"validation must be in \(0, 1\)"),
        ({"warmup": 16}, "leaves no training samples"),
    ],
)
def test_bad_selection_input(kwargs, match):
    args = {"penalties": [0.0, 1.0], **kwargs}
    x = torch.sin(torch.linspace(0, 12, 20, dtype=torch.float64))
    with pytest.raises(ValueError, match=match):
        select_penalty(x, x, args.pop("penalties"), n=3, **args)


def test_samples_outside_the_range_warn_once():
    x = torch.sin(torch.linspace(0, 30, 400, dtype=torch.float64)).repeat(2, 1)
    x[0, :50] = 2.0  # 50 of 800 samples beyond hi
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit = fit_preisach(x, x, lo=-1.0, hi=1.0, n=4)
    messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(messages) == 1 and "6.25% of the samples of x lie outside" in messages[0]
    assert caught[0].filename == __file__
    with torch.no_grad():  # saturated: every relay up
        torch.testing.assert_close(relay_states(x[:1, :50], fit.alpha, fit.beta),
                                   torch.ones(1, 50, fit.n_relays, dtype=torch.float64))


def test_loaded_grid_sets_the_range():
    """A model loaded from another's state dict reports the loaded grid's range (repr)."""
    src = Preisach(-2.0, 3.0, 5)
    dst = Preisach(0.0, 1.0, 5)
    dst.load_state_dict(src.state_dict())
    assert dst.lo == pytest.approx(-2.0) and dst.hi == pytest.approx(3.0)
    torch.testing.assert_close(dst.alpha, src.alpha)


def test_a_constant_input_without_a_range_is_named():
    x = torch.ones(1, 20, dtype=torch.float64)
    y = torch.linspace(0.0, 1.0, 20, dtype=torch.float64)[None]
    with pytest.raises(ValueError, match=r"x is constant \(1\): its range gives no grid; give lo"):
        fit_preisach(x, y)
    with pytest.raises(ValueError, match="x is constant"):
        select_penalty(x, y, [0.0, 1e-3], lo=None, hi=None, n=4)
    with pytest.raises(TypeError, match="penalties must be a sequence of candidate values"):
        select_penalty(y, y, 0.1, n=4)
    p, scores = select_penalty(y, y, np.array([0.0, 1e-2]), n=4)  # an array is a sequence
    assert p in (0.0, 1e-2) and len(scores) == 2
    m = fit_preisach(x, y, lo=0.0, n=4)  # one bound given: the grid is [0, 1]
    assert (m.lo, m.hi) == (0.0, 1.0)
