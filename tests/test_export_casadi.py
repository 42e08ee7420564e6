"""The CasADi export (torchhys.deploy.export_casadi): the compensator's step as a
casadi.Function equals the TorchScript file's step over a record with turning points, ties,
excursions, NaN and inf (commands and final state within 1e-12 of their scale), for every
registered operator (most with the slow tests) and a composition; a conditioned model's
equals the torch compensator's; its Jacobians equal torch autograd's of the explicit step
away from kinks; the C of ``Function.generate`` compiles with the C export's flags and,
run by a small driver, gives the same commands; the forward model of an operator equals its
sequence path and its Jacobian autograd's; ``NAME.casadi`` round-trips; float32
parameters step as the float32 file within 1e-4; the C templates' operations that no
operator uses translate as torch computes them; an operation without a translation is
named with its step; without casadi the error names the extra."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

casadi = pytest.importorskip("casadi")

sys.path.insert(0, str(Path(__file__).parent))
from _compose_models import CONFORMANCE, with_ranges  # noqa: E402
from _export_helpers import (  # noqa: E402
    CC,
    FLAGS,
    FLOAT32_RTOL,
    NO_CC,
    gap,
    record,
    run_torchscript,
)
from _helpers import loop_net  # noqa: E402

from torchhys import Backlash, PrandtlIshlinskii  # noqa: E402
from torchhys.deploy.export_casadi import (  # noqa: E402
    forward_function_and_state,
    function_and_state,
    load_casadi,
    save_casadi,
    to_casadi,
    to_casadi_forward,
)
from torchhys.deploy.streaming import StreamingCompensator  # noqa: E402
from torchhys.registry import OPERATORS, load_entry_points  # noqa: E402
from torchhys.step import OperatorStep, StateBlock  # noqa: E402
from torchhys.testing import example_of  # noqa: E402

load_entry_points()
NAMES = sorted(OPERATORS)
FAST = ("backlash", "eiho")  # a play network; EIHO's gathers and scatters at a counter
TOL = 1e-12
N = 2000


def _net(name: str) -> torch.nn.Module:
    torch.manual_seed(0)
    op = example_of(name).build().to(torch.float64)
    if not op.causal:
        pytest.skip(f"{type(op).__name__} is not causal: it cannot stream or be exported")
    return loop_net([op])


def _stepped(step: object, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The CasADi step over ``x`` from the fresh state: commands, final flat state."""
    s, us = step.initial_state, []
    for v in x:
        u, s = step.function(float(v), s)
        us.append(float(u))
    return np.array(us), np.asarray(s, dtype=np.float64).reshape(-1)


def _assert_as_torchscript(model: torch.nn.Module, tmp_path: Path) -> None:
    net_min, net_max = float(model.in_min), float(model.in_max)
    x = record(net_min, net_max, n=N)
    ts = run_torchscript(model, x, tmp_path / "comp.pt")
    step = function_and_state(model)
    u, s = _stepped(step, x)
    assert gap(u, ts["u"]) <= TOL
    for got, want in zip(step.unflatten(s), ts["state"], strict=True):
        assert got.dtype == want.dtype and got.shape == want.shape
        assert gap(got.double(), want.double()) <= TOL
    held, clamped = step.unflatten(s)[1][0, 0], step.unflatten(s)[1][0, -1]
    assert int(held) == int((~np.isfinite(x)).sum()) and int(clamped) > 0


@pytest.mark.parametrize("name", [pytest.param(n, marks=[pytest.mark.slow] * (n not in FAST))
                                  for n in NAMES])
def test_casadi_step_equals_torchscript(name: str, tmp_path: Path) -> None:
    _assert_as_torchscript(_net(name), tmp_path)


def test_float32_parameters_step_as_the_float32_file(tmp_path: Path) -> None:
    """dtype=torch.float32: the parameters rounded to float32, the arithmetic in float64
    (CasADi's only type), against the float32 TorchScript file within FLOAT32_RTOL; the
    counters equal."""
    net = _net("backlash")
    x = record(float(net.in_min), float(net.in_max), n=N)
    ts = run_torchscript(net, x, tmp_path / "comp.pt", torch.float32)
    step = function_and_state(net, dtype=torch.float32)
    assert step.layout[0].dtype == torch.float32
    u, s = _stepped(step, x)
    assert gap(u, ts["u"]) <= FLOAT32_RTOL
    got = step.unflatten(s)
    assert gap(got[0].double(), ts["state"][0].double()) <= FLOAT32_RTOL
    assert torch.equal(got[1], ts["state"][1]) and torch.equal(got[2], ts["state"][2])


@pytest.mark.parametrize("name", [pytest.param(n, marks=[pytest.mark.slow] * (
    n != "backlash_lstm")) for n in CONFORMANCE])
def test_composed_casadi_step_equals_torchscript(name: str, tmp_path: Path) -> None:
    """Recurrent layers (LSTM, GRU, RNN), state-space layers and MLPs too."""
    _assert_as_torchscript(with_ranges(CONFORMANCE[name]), tmp_path)


def test_conditioned_step_takes_the_conditions() -> None:
    from test_conditions import _model, _record

    x, c, y = _record()
    m = _model().fit(x, c, y)
    step = function_and_state(m, direction="none")
    assert step.n_conditions == 1
    assert step.function.name_in() == ["x", "conditions", "state"]
    xs, cs = x[1].clone(), c[1, :, 0].clone()
    cs[50], cs[80], xs[120] = float("nan"), 10.0, float("nan")
    comp = StreamingCompensator(m, direction="none")
    s, gaps = step.initial_state, []
    for k in range(len(xs)):
        u, s = step.function(float(xs[k]), float(cs[k]), s)
        want = comp.step(xs[k:k + 1], cs[k].view(1, 1))
        gaps.append(abs(float(u) - float(want)))
    assert max(gaps) <= TOL
    for got, want in zip(step.unflatten(s), comp.state, strict=True):
        assert gap(got.double(), want.double()) <= TOL


def _jacobians(step: object, comp: StreamingCompensator, x: float, flat: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """d(u, new float state)/d(x, float state) at (x, flat): CasADi's, torch autograd's."""
    f64 = [k for k, s in enumerate(step.layout) if s.dtype.is_floating_point]
    cols = np.concatenate([np.arange(step.layout[k].offset, step.layout[k].offset
                                     + step.layout[k].size) for k in f64])
    fn = step.function
    xs, ss = fn.sx_in(0), fn.sx_in(1)
    u, new = fn(xs, ss)
    jac = casadi.Function("j", [xs, ss], [casadi.jacobian(casadi.vertcat(u, new[cols]),
                                                          casadi.vertcat(xs, ss[cols]))])
    got = np.asarray(jac(x, flat))
    state = step.unflatten(flat)

    def torch_step(xt: torch.Tensor, *floats: torch.Tensor) -> torch.Tensor:
        full = list(state)
        for k, t in zip(f64, floats, strict=True):
            full[k] = t
        v, new_state = comp.step_explicit(xt, full)
        return torch.cat([v.reshape(-1), *(new_state[k].reshape(-1) for k in f64)])

    args = (torch.tensor([x], dtype=torch.float64), *(state[k] for k in f64))
    parts = torch.autograd.functional.jacobian(torch_step, args)
    want = np.concatenate([p.reshape(p.shape[0], -1).numpy() for p in parts], axis=1)
    return got, want


def test_jacobians_equal_torch_autograd_away_from_kinks() -> None:
    """Along a smooth record (no ties, in the range: the clamp, the guard and the plays
    strictly on one side of their kinks), at 25 states reached by the step itself."""
    net = loop_net([Backlash(torch.tensor([0.05, 0.2, 0.5], dtype=torch.float64))])
    comp = StreamingCompensator(net).eval()
    step = function_and_state(net)
    t = np.arange(400)
    x = 0.8 * np.sin(2 * np.pi * t / 150) * (0.6 + 0.4 * np.cos(2 * np.pi * t / 270)) \
        + 1e-3 * np.random.default_rng(0).standard_normal(len(t))
    s, worst, moving = step.initial_state, 0.0, 0
    for k, v in enumerate(x):
        if k > 20 and k % 15 == 0:
            got, want = _jacobians(step, comp, float(v), np.asarray(s).reshape(-1))
            worst = max(worst, float(np.abs(got - want).max()))
            moving += int(np.abs(want[0, 0]) > 0)
        _, s = step.function(float(v), s)
    assert worst <= 1e-12 and moving >= 10


def test_generated_c_compiles_and_runs_as_the_function(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """``Function.generate`` C, compiled with the C export's flags (but
    -Wno-unused-parameter: CasADi's calling convention passes work arrays a small
    function does not use) and run by a driver over a record with NaN and inf."""
    if CC is None:
        pytest.skip(NO_CC)
    net = _net("backlash")
    step = function_and_state(net, name="comp")
    fn = step.function
    monkeypatch.chdir(tmp_path)  # Function.generate writes into the working folder
    fn.generate("comp.c", {"with_header": True})
    n = fn.size1_in(1)
    driver = f"""
#include <stdio.h>
#include "comp.h"
int main(void) {{
    casadi_real x, u, s[{n}], t[{n}], w[{max(fn.sz_w(), 1)}];
    casadi_int iw[{max(fn.sz_iw(), 1)}];
    const casadi_real *arg[{max(fn.sz_arg(), 2)}];
    casadi_real *res[{max(fn.sz_res(), 2)}];
    int i;
    for (i = 0; i < {n}; ++i) s[i] = 0;
    while (fread(&x, sizeof x, 1, stdin) == 1) {{
        arg[0] = &x; arg[1] = s; res[0] = &u; res[1] = t;
        if (comp(arg, res, iw, w, 0)) return 1;
        for (i = 0; i < {n}; ++i) s[i] = t[i];
        fwrite(&u, sizeof u, 1, stdout);
    }}
    return 0;
}}
"""
    (tmp_path / "main.c").write_text(driver)
    exe = tmp_path / "run"
    subprocess.run([CC, *FLAGS, "-Wno-unused-parameter", "-I", str(tmp_path), "-o", str(exe),
                    str(tmp_path / "main.c"), str(tmp_path / "comp.c"), "-lm"], check=True)
    x = record(float(net.in_min), float(net.in_max), n=N)
    done = subprocess.run([str(exe)], input=x.astype(np.float64).tobytes(),
                          capture_output=True, check=True)
    u_c = np.frombuffer(done.stdout, dtype=np.float64)
    u, _ = _stepped(step, x)
    assert len(u_c) == N and gap(u_c, u) <= TOL


def test_forward_model_is_the_operators_sequence_path() -> None:
    op = PrandtlIshlinskii(torch.linspace(0.1, 1.5, 8, dtype=torch.float64),
                           torch.linspace(0.3, 0.05, 8, dtype=torch.float64),
                           linear_weight=0.2)
    fwd = forward_function_and_state(op)
    assert fwd.function.name_in() == ["u", "state"] and fwd.function.name_out()[0] == "y"
    t = torch.linspace(0, 6 * torch.pi, 300, dtype=torch.float64)
    u = torch.sin(t) * torch.linspace(0.2, 2.0, 300, dtype=torch.float64)
    want = op(u[None])[0][0]
    s, ys = fwd.initial_state, []
    for v in u.tolist():
        y, s = fwd.function(v, s)
        ys.append(float(y))
    assert gap(np.array(ys), want) <= TOL
    # dy/du is the weights of the moving plays plus the linear weight; against autograd
    step = op.streaming_step(torch.float64)
    state = fwd.unflatten(s)
    ut = torch.tensor([[0.5 * float(u[-1]) + 0.31]], dtype=torch.float64)
    jt = torch.autograd.functional.jacobian(lambda a, b: step(a, [b])[0], (ut, state[0]))
    us, ss = fwd.function.sx_in(0), fwd.function.sx_in(1)
    y = fwd.function(us, ss)[0]
    jac = casadi.Function("j", [us, ss], [casadi.jacobian(y, casadi.vertcat(us, ss))])
    got = np.asarray(jac(float(ut), np.asarray(s)))
    want_j = np.concatenate([jt[0].reshape(1, -1).numpy(), jt[1].reshape(1, -1).numpy()], 1)
    assert np.abs(got - want_j).max() <= 1e-12


def test_saved_function_loads_without_torchhys_and_steps_the_same(tmp_path: Path) -> None:
    net = _net("backlash")
    step = function_and_state(net)
    path = save_casadi(step.function, tmp_path / "torchhys_comp.casadi")
    x = record(float(net.in_min), float(net.in_max), n=300)
    code = ("import sys, casadi, numpy as np\n"
            "f = casadi.Function.load(sys.argv[1])\n"
            f"s = np.zeros({len(step.initial_state)})\n"
            "for v in np.frombuffer(sys.stdin.buffer.read()):\n"
            "    u, s = f(v, s)\n"
            "    sys.stdout.buffer.write(np.float64(float(u)).tobytes())\n")
    done = subprocess.run([sys.executable, "-c", code, path], input=x.tobytes(),
                          capture_output=True, check=True, cwd=tmp_path)
    u, _ = _stepped(step, x)
    assert np.array_equal(np.frombuffer(done.stdout, dtype=np.float64), u)
    assert load_casadi(path).name() == "torchhys_comp"
    with pytest.raises(TypeError, match="fn must be a casadi.Function"):
        save_casadi("not a function", tmp_path / "x.casadi")


class _GammaStep(OperatorStep):
    """A step with an operation that has no CasADi translation (lgamma)."""

    def __init__(self) -> None:
        super().__init__()
        self.n_outputs = 1
        self.state_spec = [StateBlock("s", 1)]

    def forward(self, x: torch.Tensor, state: list[torch.Tensor]
                ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        return torch.lgamma(x + 2.0) + state[0], [state[0] + x]


def test_an_operation_without_a_translation_is_named_with_its_step() -> None:
    with pytest.raises(ValueError) as err:
        to_casadi_forward(_GammaStep())
    msg = str(err.value)
    assert "\n" not in msg and "aten.lgamma.default" in msg and "_GammaStep" in msg
    assert "test_export_casadi.py" in msg and msg.startswith("to_casadi_forward: no CasADi")


def test_bad_arguments_are_named() -> None:
    with pytest.raises(ValueError, match="name must be an identifier"):
        to_casadi(_net("backlash"), name="not a name")
    with pytest.raises(TypeError, match="operator must be a hysteresis operator"):
        to_casadi_forward(torch.nn.Linear(1, 1))


def test_without_casadi_the_error_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    net = _net("backlash")
    monkeypatch.setitem(sys.modules, "casadi", None)  # import casadi raises ImportError
    with pytest.raises(ImportError) as err:
        to_casadi(net)
    assert str(err.value) == ('the CasADi export needs casadi: pip install '
                              '"torchhys[casadi]"')


class _ManyOps(torch.nn.Module):
    """Operations of the C templates that the registered operators do not use (x (1, 6))."""

    def __init__(self) -> None:
        super().__init__()
        self.bn = torch.nn.BatchNorm1d(6).double().eval()
        with torch.no_grad():
            self.bn.running_mean.copy_(torch.linspace(-0.2, 0.3, 6))
            self.bn.running_var.copy_(torch.linspace(0.5, 2.0, 6))
        self.register_buffer("knots", torch.linspace(-1.0, 1.0, 5, dtype=torch.float64))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = torch.nn.functional
        a, b, c = torch.tensor_split(x, 3, dim=1)
        outer = x.reshape(6, 1) * x.reshape(1, 6)
        k = torch.searchsorted(self.knots, x.reshape(-1).contiguous()).clamp(0, 4)
        parts = [
            x.flip(1), torch.diagonal(outer, 1).reshape(1, -1), f.logsigmoid(x),
            f.rms_norm(x, [6], eps=1e-6), self.bn(x), f.softmax(x, 1), f.log_softmax(x, 1),
            f.layer_norm(x, [6]), f.gelu(x), f.softplus(x), f.elu(x), f.hardswish(x),
            torch.remainder(x, 0.3), torch.fmod(x, 0.3), torch.atan2(x, a.sum() + 2.0),
            x.cumsum(1), x.amax(1, keepdim=True), x.mean(1, keepdim=True),
            (x > 0).any(1, keepdim=True).double(), (x > -2).all(1, keepdim=True).double(),
            torch.where(x > b.mean(), x.sinh(), c.sum() ** 3),
            x.sort(1).values, self.knots[k].reshape(1, -1), x.abs().pow(1.5),
            torch.stack(x.unbind(1), 0).reshape(1, -1) * 2.0,
            x.gather(1, (k % 6).reshape(1, -1)), x.index_select(1, 5 - k),
        ]
        return torch.cat(parts, 1)


def test_the_c_templates_operations_translate_as_torch_computes() -> None:
    from torchhys.deploy.casadi._values import Sym, objects
    from torchhys.deploy.casadi._walk import translate

    module = _ManyOps()
    with torch.no_grad():
        ep = torch.export.export(module, (torch.zeros(1, 6, dtype=torch.float64),),
                                 strict=False)
    xs = casadi.SX.sym("x", 6)
    (out,) = translate(ep, [Sym(objects([xs[i] for i in range(6)], (1, 6)), torch.float64)])
    fn = casadi.Function("many", [xs], [casadi.vertcat(*out.a.flat)])
    g = np.random.default_rng(0)
    for _ in range(20):
        x = g.uniform(-1.5, 1.5, 6)
        with torch.no_grad():
            want = module(torch.tensor(x[None])).reshape(-1).numpy()
        got = np.asarray(fn(x)).reshape(-1)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def _cli_ckpt(tmp_path: Path) -> tuple[Path, torch.nn.Module]:
    sys.path.insert(0, str(Path(__file__).parent))
    from test_export_cli import lightning_ckpt, trained

    net = trained().double()
    torch.save(lightning_ckpt(net), tmp_path / "m.ckpt")
    return tmp_path / "m.ckpt", net


def test_the_cli_writes_the_casadi_file_of_the_torchscript_step(tmp_path: Path,
                                                                capsys) -> None:
    from torchhys.cli.export import main

    ckpt, _ = _cli_ckpt(tmp_path)
    rc = main(["--ckpt", str(ckpt), "--format", "casadi", "--out", str(tmp_path / "c.casadi"),
               "--limits", "-2", "2", "--prefix", "comp"])
    assert rc == 0 and "c.casadi (casadi, float64)" in capsys.readouterr().out
    rc = main(["--ckpt", str(ckpt), "--format", "torchscript", "--out", str(tmp_path / "c.pt"),
               "--limits", "-2", "2"])
    assert rc == 0
    fn = load_casadi(tmp_path / "c.casadi")
    assert fn.name() == "comp"
    from torchhys.deploy.export import load_torchscript
    module = load_torchscript(tmp_path / "c.pt")
    x = 3.5 * np.sin(np.linspace(0.0, 25.0, 400))  # beyond the range: clamped
    s = np.zeros(fn.size1_in(1))
    worst = 0.0
    for v in x:
        u, s = fn(float(v), s)
        want = module.step(torch.tensor([v], dtype=torch.float64))
        worst = max(worst, abs(float(u) - float(want[0])))
    assert worst <= 1e-12


@pytest.mark.parametrize(("extra", "message"), [
    (["--adapt", "rls"], "--adapt applies to the torchscript, aoti, c, onnx and fmu formats"),
    ([], "must end in .casadi (--format casadi)"),
])
def test_the_cli_names_what_casadi_refuses(tmp_path: Path, capsys, extra: list,
                                           message: str) -> None:
    from torchhys.cli.export import main

    ckpt, _ = _cli_ckpt(tmp_path)
    out = tmp_path / ("c.casadi" if extra else "c.bin")
    rc = main(["--ckpt", str(ckpt), "--format", "casadi", "--out", str(out), *extra])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_the_cli_without_casadi_names_the_extra(tmp_path: Path, capsys,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    from torchhys.cli.export import main

    ckpt, _ = _cli_ckpt(tmp_path)
    monkeypatch.setitem(sys.modules, "casadi", None)
    rc = main(["--ckpt", str(ckpt), "--format", "casadi", "--out", str(tmp_path / "c.casadi")])
    err = capsys.readouterr().err
    assert rc == 2 and 'pip install "torchhys[casadi]"' in err
    assert len(err.strip().splitlines()) == 1, err
