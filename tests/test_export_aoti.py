"""torch.export + AOTInductor: the compiled step equals eager (slow: compiling takes a minute)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from _helpers import RAW, inputs, net_of

from torchhys import EIHO, Backlash
from torchhys.deploy.export import load_aoti, state_spec_string, to_aoti
from torchhys.deploy.streaming import StreamingCompensator

LIMITS = (-50.0, 50.0)


@pytest.fixture(scope="module")
def package(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    x = inputs(300).float()
    ops = [EIHO(a=(1.2, 0.8), rule="dominant", threshold=0.25, max_depth=8),
           EIHO(a="learnable", rule="recent"), Backlash([0.0, 0.4, 1.5])]
    net = net_of(ops, torch.float32, x)
    path = tmp_path_factory.mktemp("aoti") / "comp.pt2"
    to_aoti(net, path, limits=LIMITS, **RAW)
    return net, str(path)


@pytest.mark.slow
def test_aoti_equals_eager_step_by_step(package: tuple) -> None:
    net, path = package
    x = inputs(300).float()
    eager = StreamingCompensator(net, limits=LIMITS, **RAW)
    with torch.no_grad():
        ref, _ = net(x)
    runner = load_aoti(path)
    for row in range(x.shape[0]):
        runner.reset()
        u = torch.cat([runner.step(xt[None]) for xt in x[row]])
        torch.testing.assert_close(u, eager(x[row]), rtol=0, atol=1e-6)
        torch.testing.assert_close(u, ref[row], rtol=0, atol=1e-6)


@pytest.mark.slow
def test_aoti_metadata_and_nan_hold(package: tuple) -> None:
    net, path = package
    runner = load_aoti(path)
    assert runner.spec == state_spec_string(StreamingCompensator(net, limits=LIMITS, **RAW))
    assert (runner.low, runner.high) == LIMITS
    x = inputs(60).float()[0]
    u1 = [runner.step(x[t:t + 1]) for t in range(30)]
    held = runner.step(torch.tensor([float("inf")]))
    assert torch.equal(held, u1[-1]) and int(runner.nonfinite_count()) == 1


@pytest.mark.slow
def test_aoti_loads_without_torchhys(package: tuple, tmp_path: Path) -> None:
    _, path = package
    script = textwrap.dedent(
        f"""
        import sys
        sys.modules["torchhys"] = None
        import torch
        runner = torch._inductor.aoti_load_package({path!r})
        meta = runner.get_metadata()
        state = []
        for part in meta["state_spec"].split(";"):
            name, dims = part.split(":")
            shape = [int(d) for d in dims.split(",") if d]
            state.append(torch.zeros(shape, dtype=getattr(torch, name)))
        out = runner(torch.tensor([0.5]), *state)
        assert len(out) == 1 + len(state) and torch.isfinite(out[0]).all()
        print("ok")
        """
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    res = subprocess.run([sys.executable, "-I", "-c", script], capture_output=True, text=True,
                         env=env, cwd=tmp_path, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.strip().endswith("ok")


def test_aoti_bad_arguments(tmp_path: Path) -> None:
    net = net_of([Backlash([0.5])], torch.float32, inputs(50).float())
    with pytest.raises(ValueError, match="batch"):
        to_aoti(net, tmp_path / "m.pt2", limits=LIMITS, batch=0)
    with pytest.raises(ValueError, match="directory"):
        to_aoti(net, tmp_path / "no" / "m.pt2", limits=LIMITS, **RAW)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_aoti_batch_rows_equal_eager(dtype: torch.dtype, tmp_path: Path) -> None:
    """A package compiled at batch 5, driven with strided columns ``x[:, t]``, equals eager
    row by row (regression: the kernels read a non-contiguous sample as ``x[0, t:t + 5]``)."""
    x = inputs(200).to(dtype)
    ops = [EIHO(a=0.9, rule="recent", output="branch"),
           EIHO(a=(1.2, 0.8), rule="dominant", threshold=0.25, max_depth=6),
           Backlash([0.0, 0.4, 1.5])]
    net = net_of(ops, dtype, x)
    path = to_aoti(net, tmp_path / "comp.pt2", limits=LIMITS, batch=x.shape[0], **RAW)
    runner = load_aoti(path)
    u = torch.stack([runner.step(x[:, t]) for t in range(x.shape[1])], 1)
    atol = 1e-6 if dtype == torch.float32 else 1e-12
    with torch.no_grad():
        ref, _ = net(x)
    for row in range(x.shape[0]):  # each row alone through eager, batch 1
        alone = StreamingCompensator(net, limits=LIMITS, **RAW)(x[row])
        torch.testing.assert_close(u[row], alone, rtol=0, atol=atol)
        torch.testing.assert_close(u[row], ref[row], rtol=0, atol=atol)
    with pytest.raises(ValueError, match="compiled batch"):
        runner.step(x[:2, 0])
