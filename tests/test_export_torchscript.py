"""TorchScript export: scripted equals eager, loads without torchhys, safety survives export."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import warnings

import pytest
import torch
from _helpers import RAW, inputs, net_of

from torchhys import EIHO, Backlash, PrandtlIshlinskii, ZhaoTanOperator
from torchhys.deploy.export import load_torchscript, to_torchscript
from torchhys.deploy.streaming import StreamingCompensator

CONFIGS = {
    "eiho_dominant_plays": lambda: [EIHO(a=(1.2, 0.8), rule="dominant", threshold=0.25,
                                         max_depth=8), Backlash([0.2, 0.7, 1.5])],
    "eiho_learnable_recent": lambda: [EIHO(a="learnable", rule="recent", threshold=0.0)],
    "zhao_tan": lambda: [ZhaoTanOperator(rule="dominant", threshold=0.5, scale=2.0)],
    "plays": lambda: [Backlash(torch.linspace(0.1, 2.0, 8))],
}


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> dict:
    x = inputs(300).float()
    out = {}
    for name, make in CONFIGS.items():
        net = net_of(make(), torch.float32, x)
        path = tmp_path_factory.mktemp(name) / "comp.pt"
        to_torchscript(net, path, limits=(-50.0, 50.0), **RAW)
        out[name] = (net, str(path))
    return out


@pytest.mark.parametrize("name", list(CONFIGS))
def test_scripted_equals_eager(exported: dict, name: str) -> None:
    net, path = exported[name]
    x = inputs(300).float()
    with torch.no_grad():
        ref, _ = net(x)
    eager = StreamingCompensator(net, limits=(-50.0, 50.0), **RAW)
    loaded = load_torchscript(path)
    seq = loaded(x)
    torch.testing.assert_close(seq, ref, rtol=0, atol=1e-6)
    torch.testing.assert_close(seq, eager(x), rtol=0, atol=1e-6)
    loaded.reset()
    steps = torch.stack([loaded.step(xt) for xt in x.unbind(-1)], dim=-1)
    torch.testing.assert_close(steps, seq, rtol=0, atol=0)  # forward == steps after reset
    loaded.reset()
    torch.testing.assert_close(loaded.step(x[:, 0]), seq[:, 0], rtol=0, atol=0)


def test_safety_survives_export(exported: dict) -> None:
    _, path = exported["eiho_dominant_plays"]
    m = load_torchscript(path)
    x = inputs(100).float()[:1]
    clean = m(x)[0]
    m.reset()
    out = []
    for t in range(100):
        if t == 40:
            out.append(m.step(torch.tensor([float("nan")])))
        out.append(m.step(x[:, t]))
    assert int(m.nonfinite_count()) == 1
    assert out[40] == out[39]
    torch.testing.assert_close(torch.cat(out[:40] + out[41:]), clean, rtol=0, atol=0)
    assert float(m.low) == -50.0 and float(m.high) == 50.0


def test_pi_inverse_exports(tmp_path) -> None:
    pi = PrandtlIshlinskii(torch.linspace(0.2, 2.0, 6), linear_weight=0.5)
    inv = pi.inverse()
    y = 3 * torch.sin(torch.linspace(0, 12, 400))
    m = to_torchscript(inv, tmp_path / "pi.pt", limits=(-100.0, 100.0), **RAW)
    torch.testing.assert_close(m(y), inv(y)[0], rtol=0, atol=1e-6)


def test_only_the_deprecation_warning_is_caught(tmp_path) -> None:
    x = inputs(50).float()
    net = net_of(CONFIGS["plays"](), torch.float32, x)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        before = list(warnings.filters)
        to_torchscript(net, tmp_path / "m.pt", limits=(-1.0, 1.0), **RAW)
        load_torchscript(tmp_path / "m.pt")
        assert list(warnings.filters) == before  # nothing silenced globally
    messages = [str(w.message) for w in caught]
    assert not any("torch.jit.script" in m or "torch.jit.load" in m for m in messages)


def test_bad_path_and_model(tmp_path) -> None:
    x = inputs(50).float()
    net = net_of(CONFIGS["plays"](), torch.float32, x)
    with pytest.raises(ValueError, match="directory"):
        to_torchscript(net, tmp_path / "missing" / "m.pt")
    with pytest.raises(TypeError, match="path"):
        to_torchscript(net, 3)
    with pytest.raises(TypeError, match="InverseHysteresisNet"):
        to_torchscript(torch.nn.Linear(1, 1), tmp_path / "m.pt", limits=(-1.0, 1.0))
    with pytest.raises(ValueError, match="limits"):
        to_torchscript(net, tmp_path / "m.pt", limits=(1.0, -1.0), **RAW)


def test_loads_in_a_fresh_process_without_torchhys(exported: dict, tmp_path) -> None:
    _, path = exported["eiho_dominant_plays"]
    x = inputs(200).float()
    ref = load_torchscript(path)(x)
    torch.save({"x": x, "ref": ref}, tmp_path / "data.pt")
    script = textwrap.dedent(
        f"""
        import sys
        sys.modules["torchhys"] = None  # importing torchhys must fail here
        try:
            import torchhys  # noqa: F401
        except ImportError:
            pass
        else:
            raise SystemExit("torchhys was importable")
        import torch
        d = torch.load({str(tmp_path / "data.pt")!r})
        m = torch.jit.load({path!r})
        torch.testing.assert_close(m(d["x"]), d["ref"], rtol=0, atol=0)
        m.reset()
        u = torch.stack([m.step(xt) for xt in d["x"].unbind(-1)], -1)
        torch.testing.assert_close(u, d["ref"], rtol=0, atol=0)
        m.step(torch.full((5,), float("nan")))
        assert m.nonfinite_count().tolist() == [1] * 5
        print("ok")
        """
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    res = subprocess.run([sys.executable, "-I", "-c", script], capture_output=True, text=True,
                         env=env, cwd=tmp_path, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "ok"


def test_scripted_batch_rows_equal_eager(tmp_path) -> None:
    """Batch 5 through the scripted step (strided columns ``x[:, t]``) equals each row run
    alone through eager, for the deployed EIHO network (float64)."""
    x = inputs(200)
    net = net_of([EIHO(a=0.9, rule="recent", output="branch"), Backlash([0.0, 0.4, 1.5])],
                 torch.float64, x)
    to_torchscript(net, tmp_path / "comp.pt", limits=(-50.0, 50.0), **RAW)
    loaded = load_torchscript(tmp_path / "comp.pt")
    u = torch.stack([loaded.step(x[:, t]) for t in range(x.shape[1])], 1)
    with torch.no_grad():
        ref, _ = net(x)
    for row in range(x.shape[0]):
        alone = StreamingCompensator(net, limits=(-50.0, 50.0), **RAW)(x[row])
        torch.testing.assert_close(u[row], alone, rtol=0, atol=1e-12)
        torch.testing.assert_close(u[row], ref[row], rtol=0, atol=1e-12)
