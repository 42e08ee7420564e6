"""The co-simulation FMU (torchhys.deploy.export_fmu.to_fmu, ``torchhys export --format fmu``):
FMPy validates it (FMI 2.0 and 3.0); FMPy's simulation of a record (turning points, ties,
signed zeros, excursions beyond the training range, NaN and inf) equals the TorchScript
file's commands within 1e-12 of their scale in float64 and its counters exactly; the binary
rebuilt from ``sources/`` by FMPy's CMake project simulates the same; two instances side by
side each equal their own reference; a saved FMU state (in memory and serialized) restored
reruns bit for bit; a communication step that is not a multiple of the sample period is an
error status with a logged message; a conditioned model steps with its conditions; the
command line writes an FMU from a checkpoint and names the argument of a bad option."""

from __future__ import annotations

import copy
import json
import shutil
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from _export_helpers import (  # noqa: E402
    CC,
    FLOAT32_RTOL,
    NO_CC,
    gap,
    record,
    run_torchscript,
    training_range,
)
from test_export_cli import lightning_ckpt, trained  # noqa: E402

fmpy = pytest.importorskip("fmpy", reason="the fmu extra (pip install 'torchhys[fmu]')")
from fmpy import extract, read_model_description, simulate_fmu  # noqa: E402
from fmpy.fmi1 import FMICallException  # noqa: E402
from fmpy.fmi2 import FMU2Slave, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE  # noqa: E402
from fmpy.fmi3 import FMU3Slave  # noqa: E402
from fmpy.validation import validate_fmu  # noqa: E402

from torchhys.deploy.export_fmu import check_fmu, to_fmu  # noqa: E402

pytestmark = pytest.mark.skipif(CC is None, reason=NO_CC)
T = 0.01  # the sample period of the tests' FMUs
LIMITS = (-2.0, 2.0)
VR_DESIRED, VR_COMMAND = 0, 1


class Stepper:
    """An instance of an extracted FMU (FMPy's FMU2Slave or FMU3Slave), stepped sample by
    sample; the logger's messages in :attr:`messages`."""

    def __init__(self, unzipdir: str, name: str = "a") -> None:
        md = read_model_description(unzipdir)
        self.fmi = 2 if md.fmiVersion == "2.0" else 3
        self.vr = {v.name: v.valueReference for v in md.modelVariables}
        self.period = next(float(v.start) for v in md.modelVariables
                           if v.name == "sample_period")
        self.messages: list[str] = []
        kind = FMU2Slave if self.fmi == 2 else FMU3Slave
        self.fmu = kind(guid=md.guid, unzipDirectory=unzipdir, instanceName=name,
                        modelIdentifier=md.coSimulation.modelIdentifier)
        if self.fmi == 2:
            def log2(env, instance, status, category, message):  # noqa: ANN001
                self.messages.append(message.decode())
            self.callbacks = fmi2CallbackFunctions()
            self.callbacks.logger = fmi2CallbackLoggerTYPE(log2)
            self.fmu.instantiate(callbacks=self.callbacks)
            self.fmu.setupExperiment(startTime=0.0)
            self.fmu.enterInitializationMode()
        else:
            def log3(env, status, category, message):  # noqa: ANN001
                self.messages.append(message.decode())
            self.fmu.instantiate(logMessage=log3)
            self.fmu.enterInitializationMode(startTime=0.0)
        self.fmu.exitInitializationMode()
        self.t = 0.0
        self.k = 0

    def set(self, names: list[str], values: list[float]) -> None:
        vrs = [self.vr[n] for n in names]
        (self.fmu.setReal if self.fmi == 2 else self.fmu.setFloat64)(vrs, values)

    def get(self, names: list[str]) -> list[float]:
        vrs = [self.vr[n] for n in names]
        return (self.fmu.getReal if self.fmi == 2 else self.fmu.getFloat64)(vrs)

    def counts(self) -> tuple[int, int]:
        vrs = [self.vr["nonfinite_count"], self.vr["out_of_range_count"]]
        got = (self.fmu.getInteger if self.fmi == 2 else self.fmu.getInt64)(vrs)
        return int(got[0]), int(got[1])

    def step(self, h: float | None = None) -> None:
        """A communication step of ``h`` (default one sample period)."""
        h = self.period if h is None else h
        self.fmu.doStep(currentCommunicationPoint=self.t, communicationStepSize=h)
        self.k += round(h / self.period)
        self.t = self.k * self.period

    def run(self, x: np.ndarray, conditions: np.ndarray | None = None) -> np.ndarray:
        """The command after each sample of ``x`` (one sample a communication step)."""
        u = np.empty(len(x))
        for i, v in enumerate(x):
            if conditions is None:
                self.set(["desired"], [float(v)])
            else:
                self.set(["desired", "condition_0"], [float(v), float(conditions[i])])
            self.step()
            u[i] = self.get(["command"])[0]
        return u

    def get_state(self) -> object:
        return self.fmu.getFMUstate() if self.fmi == 2 else self.fmu.getFMUState()

    def set_state(self, state: object) -> None:
        (self.fmu.setFMUstate if self.fmi == 2 else self.fmu.setFMUState)(state)

    def serialize(self, state: object) -> bytes:
        return (self.fmu.serializeFMUstate if self.fmi == 2 else self.fmu.serializeFMUState)(
            state)

    def deserialize(self, data: bytes) -> object:
        return (self.fmu.deSerializeFMUstate if self.fmi == 2
                else self.fmu.deserializeFMUState)(data)

    def close(self) -> None:
        self.fmu.terminate()
        self.fmu.freeInstance()


def run_fmu(path: Path, x: np.ndarray, conditions: np.ndarray | None = None) -> dict:
    """An FMU stepped over ``x``: the commands and the two counters (the runner of the
    conformance check, tests/test_conformance.py)."""
    s = Stepper(extract(str(path)))
    u = s.run(x, conditions)
    nonfinite, oor = s.counts()
    s.close()
    return {"u": u, "nonfinite": nonfinite, "out_of_range": oor}


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The network of tests/test_export_cli.py in float64, a record of 1000 samples, the
    TorchScript file's run over it and the FMI 2 and FMI 3 FMUs."""
    folder = tmp_path_factory.mktemp("fmu")
    net = trained().double()
    x = record(*training_range(net), n=1000)
    ts = run_torchscript(net, x, folder / "comp.pt", limits=LIMITS)
    fmus = {fmi: to_fmu(net, folder / f"comp{fmi}.fmu", fmi=fmi, sample_period=T,
                        limits=LIMITS, units={"desired": "um", "command": "V"})
            for fmi in (2, 3)}
    return {"net": net, "x": x, "ts": ts, "fmus": fmus, "folder": folder}


@pytest.mark.parametrize("fmi", [2, 3])
def test_fmpy_validates_the_fmu(case: dict, fmi: int) -> None:
    path = case["fmus"][fmi]
    assert validate_fmu(str(path)) == []
    info = check_fmu(path)
    folder = "linux64" if fmi == 2 else "x86_64-linux"
    assert info["fmi"] == fmi and info["model_identifier"] == f"comp{fmi}"
    assert f"binaries/{folder}/comp{fmi}.so" in info["entries"]
    assert {f"sources/comp{fmi}.c", f"sources/comp{fmi}.h", f"sources/comp{fmi}_fmu.c"} <= set(
        info["entries"])
    assert ("sources/buildDescription.xml" in info["entries"]) == (fmi == 3)
    md = read_model_description(str(path))
    assert md.defaultExperiment.stepSize == str(T) or float(md.defaultExperiment.stepSize) == T
    names = {v.name: v for v in md.modelVariables}
    assert names["desired"].causality == "input" and names["command"].causality == "output"
    assert names["desired"].unit == "um" and names["command"].unit == "V"
    assert float(names["command_low"].start) == -2.0 and names["command_low"].variability == (
        "constant")
    assert "torchhys" in md.description and "training range" in md.description
    # the token is the content's: the wrapper holds it, it is a uuid
    with zipfile.ZipFile(path) as zf:
        assert info["token"] in zf.read(f"sources/comp{fmi}_fmu.c").decode()


@pytest.mark.parametrize("fmi", [2, 3])
def test_simulate_fmu_equals_the_torchscript_file(case: dict, fmi: int) -> None:
    """FMPy's simulate_fmu with the record as a structured array: the command read at
    ``(k + 1) T`` is the sample ``k``'s (no direct feedthrough) and equals the TorchScript
    file's within 1e-12 of its scale; the counters equal."""
    x, ts = case["x"], case["ts"]
    signal = np.zeros(len(x), dtype=[("time", np.float64), ("desired", np.float64)])
    signal["time"], signal["desired"] = np.arange(len(x)) * T, x
    res = simulate_fmu(str(case["fmus"][fmi]), input=signal, stop_time=len(x) * T,
                       output=["command", "nonfinite_count", "out_of_range_count"])
    assert len(res) == len(x) + 1 and res["command"][0] == 0.0  # the initial command
    assert gap(res["command"][1:], ts["u"]) <= 1e-12
    assert (res["nonfinite_count"][-1], res["out_of_range_count"][-1]) == (
        ts["nonfinite"], ts["out_of_range"])
    assert ts["nonfinite"] == int((~np.isfinite(x)).sum()) and ts["out_of_range"] > 0


@pytest.mark.parametrize("fmi", [2, pytest.param(3, marks=pytest.mark.slow)])
def test_fmpy_rebuilds_the_binary_from_the_sources(case: dict, fmi: int,
                                                   tmp_path: Path) -> None:
    """FMPy's CMake project (fmpy.build.build_platform_binary) compiles ``sources/`` from
    scratch; the rebuilt binary steps the record as the TorchScript file."""
    if shutil.which("cmake") is None:
        pytest.skip("no cmake on PATH")
    from fmpy.build import build_platform_binary

    unzipdir = tmp_path / "fmu"
    with zipfile.ZipFile(case["fmus"][fmi]) as zf:
        zf.extractall(unzipdir)
    shutil.rmtree(unzipdir / "binaries")
    build_platform_binary(unzipdir, build_dir=None)
    assert list((unzipdir / "binaries").rglob(f"comp{fmi}.so"))
    s = Stepper(str(unzipdir))
    assert gap(s.run(case["x"]), case["ts"]["u"]) <= 1e-12
    assert s.counts() == (case["ts"]["nonfinite"], case["ts"]["out_of_range"])
    s.close()


@pytest.mark.parametrize("fmi", [2, 3])
def test_two_instances_side_by_side(case: dict, fmi: int) -> None:
    """Two instances of one binary stepped alternately on different records: each equals
    its own reference (no state shared between instances)."""
    x = case["x"][:400]
    y = 0.5 * x[::-1].copy()
    ref_y = run_torchscript(case["net"], y, case["folder"] / f"y{fmi}.pt", limits=LIMITS)
    unzipdir = extract(str(case["fmus"][fmi]))
    a, b = Stepper(unzipdir, "a"), Stepper(unzipdir, "b")
    ua, ub = np.empty(len(x)), np.empty(len(y))
    for i in range(len(x)):
        a.set(["desired"], [float(x[i])])
        b.set(["desired"], [float(y[i])])
        a.step()
        b.step()
        ua[i], ub[i] = a.get(["command"])[0], b.get(["command"])[0]
    assert gap(ua, case["ts"]["u"][:400]) <= 1e-12 and gap(ub, ref_y["u"]) <= 1e-12
    assert not np.array_equal(ua, ub)
    a.close()
    b.close()


@pytest.mark.parametrize("fmi", [2, 3])
def test_fmu_state_round_trips(case: dict, fmi: int) -> None:
    """Save the state at a sample, run on, restore it (in memory, then from its serialized
    bytes) and rerun: the same commands and counters, bit for bit; bytes of another length
    are refused with a logged message."""
    x = case["x"]
    s = Stepper(extract(str(case["fmus"][fmi])))
    s.run(x[:300])
    state, t, k = s.get_state(), s.t, s.k
    data = s.serialize(state)
    first = s.run(x[300:600])
    counts = s.counts()
    s.set_state(state)
    s.t, s.k = t, k
    assert np.array_equal(s.run(x[300:600]), first) and s.counts() == counts
    assert s.get(["time"])[0] == pytest.approx(600 * T)
    restored = s.deserialize(data)
    s.set_state(restored)
    s.t, s.k = t, k
    assert np.array_equal(s.run(x[300:600]), first) and s.counts() == counts
    assert gap(first, case["ts"]["u"][300:600]) <= 1e-12
    with pytest.raises(FMICallException):
        s.deserialize(data[:-1])
    assert "not a state serialized by this FMU" in s.messages[-1]
    s.close()


@pytest.mark.parametrize("fmi", [2, 3])
def test_a_step_that_is_not_a_multiple_is_an_error(case: dict, fmi: int) -> None:
    """doStep over 1.5 sample periods: an error status, the message logged, no sample run;
    a multiple (3 periods) runs 3 samples with the input held."""
    s = Stepper(extract(str(case["fmus"][fmi])))
    s.set(["desired"], [0.5])
    with pytest.raises(FMICallException):
        s.step(1.5 * T)
    assert "not a positive integer multiple of the sample period" in s.messages[-1]
    assert s.get(["time", "command"]) == [0.0, 0.0]
    with pytest.raises(FMICallException):  # not the instance's time
        s.fmu.doStep(currentCommunicationPoint=5 * T, communicationStepSize=T)
    assert "is not the instance's time" in s.messages[-1]
    s.step(3 * T)
    ref = run_torchscript(case["net"], np.full(3, 0.5), case["folder"] / f"h{fmi}.pt",
                          limits=LIMITS)
    assert s.get(["command"])[0] == pytest.approx(ref["u"][-1], abs=1e-12)
    assert s.get(["time"])[0] == pytest.approx(3 * T)
    s.set(["desired"], [float("nan")])  # three samples run: three NaN samples counted
    s.step(3 * T)
    assert s.counts()[0] == 3 and s.get(["time"])[0] == pytest.approx(6 * T)
    with pytest.raises(FMICallException):  # an output is not settable
        s.set(["command"], [1.0])
    s.close()


def test_a_float32_step(case: dict, tmp_path: Path) -> None:
    """dtype=torch.float32: the C step's real type is float (the inputs rounded to it), its
    commands within the C export's float32 tolerance (1e-4 of the scale) of the float32
    TorchScript file's, the counters equal."""
    x = case["x"]
    path = to_fmu(case["net"], tmp_path / "f32.fmu", dtype=torch.float32, limits=LIMITS)
    with zipfile.ZipFile(path) as zf:
        assert "typedef float f32_real;" in zf.read("sources/f32.h").decode()
    ts = run_torchscript(case["net"], x, tmp_path / "f32.pt", torch.float32, limits=LIMITS)
    got = run_fmu(path, x)
    assert gap(got["u"], ts["u"]) <= FLOAT32_RTOL
    assert (got["nonfinite"], got["out_of_range"]) == (ts["nonfinite"], ts["out_of_range"])


def test_a_conditioned_model_takes_its_conditions(tmp_path: Path) -> None:
    """A scheduled readout (tests/test_conditions.py): the FMU has an input condition_0 and
    its commands equal the compensator's, stepped with the conditions (float64)."""
    from test_conditions import _model, _record

    from torchhys.deploy.streaming import StreamingCompensator

    x, c, y = _record()
    m = _model().fit(x, c, y)
    path = to_fmu(m, tmp_path / "cond.fmu", sample_period=T, direction="none")
    assert validate_fmu(str(path)) == []
    names = {v.name: v for v in read_model_description(str(path)).modelVariables}
    assert names["condition_0"].causality == "input"
    xs, cs = x[1].clone(), c[1, :, 0].clone()
    cs[50], cs[80] = float("nan"), 10.0
    got = run_fmu(path, xs.numpy(), cs.numpy())
    comp = StreamingCompensator(copy.deepcopy(m), direction="none")
    ref = np.array([float(comp.step(xs[i:i + 1], cs[i:i + 1].view(1, 1)))
                    for i in range(len(xs))])
    assert gap(got["u"], ref) <= 1e-12
    assert (got["nonfinite"], got["out_of_range"]) == (int(comp.nonfinite_count()),
                                                        int(comp.out_of_range_count()))


@pytest.mark.parametrize("fmi", [2, 3])
def test_the_adaptive_step(tmp_path: Path, fmi: int) -> None:
    """adapt="rls": the inputs measured_prev and applied_prev, the three adaptation counters;
    fed the pairs of the eager compensator's closed loop (tests/test_adaptive_c.py: a drifting
    plant, NaN bursts, outliers), the commands within 1e-12 of the eager ones, the five
    counters equal; a communication step of 3 periods passes the pair to its first sample
    only (the other two skipped)."""
    from test_adaptive_c import MODELS, OPTS, closed_loop

    from torchhys.deploy.adaptive import AdaptiveCompensator

    model = MODELS["identity_net"]()
    ref = closed_loop(AdaptiveCompensator(model, adapt="rls", **OPTS), 1500)
    path = to_fmu(model, tmp_path / "ad.fmu", fmi=fmi, adapt="rls", **OPTS)
    assert validate_fmu(str(path)) == []
    s = Stepper(extract(str(path)))
    names = ["desired", "measured_prev", "applied_prev"]
    u = np.empty(len(ref["rows"]))
    for i, row in enumerate(ref["rows"]):
        s.set(names, [float(v) for v in row])
        s.step()
        u[i] = s.get(["command"])[0]
    assert gap(u, ref["u"]) <= 1e-12
    counters = ["updates_count", "skipped_count", "refused_count", "nonfinite_count",
                "out_of_range_count"]
    vrs = [s.vr[n] for n in counters]
    got = (s.fmu.getInteger if fmi == 2 else s.fmu.getInt64)(vrs)
    assert [int(v) for v in got] == ref["counts"] and ref["counts"][0] > 100
    s.set(names, [0.5, 0.4, 0.3])
    s.step(3 * s.period)
    after = (s.fmu.getInteger if fmi == 2 else s.fmu.getInt64)(vrs)
    assert after[1] - got[1] >= 2  # the second and third samples had no pair
    s.close()


def test_a_damaged_fmu_is_one_line(case: dict, tmp_path: Path) -> None:
    data = case["fmus"][2].read_bytes()
    bad = tmp_path / "cut.fmu"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="not a readable FMU") as err:
        check_fmu(bad)
    assert "\n" not in str(err.value)
    empty = tmp_path / "empty.fmu"
    with zipfile.ZipFile(empty, "w") as zf:
        zf.writestr("x.txt", "x")
    with pytest.raises(ValueError, match="modelDescription.xml"):
        check_fmu(empty)


def test_a_sources_only_fmu(case: dict, tmp_path: Path) -> None:
    path = to_fmu(case["net"], tmp_path / "src.fmu", binaries=False, fmi=3)
    assert validate_fmu(str(path)) == []
    assert not [n for n in check_fmu(path)["entries"] if n.startswith("binaries/")]


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"fmi": 4}, "fmi must be 2 or 3"),
    ({"path": "comp.zip"}, "must end in .fmu"),
    ({"path": "9lives.fmu"}, "prefix must be a C identifier"),
    ({"prefix": "a-b"}, "prefix must be a C identifier"),
    ({"step_size": 0.015, "sample_period": 0.01}, "step_size 0.015 is not an integer multiple"),
    ({"step_size": -1.0}, "step_size must be a finite number > 0"),
    ({"units": {"speed": "m/s"}}, "units: 'speed' is not a variable"),
])
def test_bad_arguments_are_one_line(case: dict, tmp_path: Path, kwargs: dict,
                                    message: str) -> None:
    kwargs = dict(kwargs)
    path = tmp_path / kwargs.pop("path", "comp.fmu")
    with pytest.raises(ValueError, match=message) as err:
        to_fmu(case["net"], path, **kwargs)
    assert "\n" not in str(err.value)


def test_the_command_line_writes_an_fmu(case: dict, tmp_path: Path, capsys) -> None:
    from torchhys.cli.export import main

    ckpt = tmp_path / "m.ckpt"
    torch.save(lightning_ckpt(case["net"]), ckpt)
    out = tmp_path / "comp.fmu"
    rc = main(["--ckpt", str(ckpt), "--format", "fmu", "--out", str(out), "--fmi", "3",
               "--step-size", "0.03", "--sample-period", "0.01", "--limits", "-2", "2"])
    assert rc == 0 and "FMI 3.0" in capsys.readouterr().out
    md = read_model_description(str(out))
    assert md.fmiVersion == "3.0" and float(md.defaultExperiment.stepSize) == 0.03
    s = Stepper(extract(str(out)))
    assert gap(s.run(case["x"][:200]), case["ts"]["u"][:200]) <= 1e-12
    s.close()


@pytest.mark.parametrize(("argv", "message"), [
    (["--fmi", "4"], "argument --fmi: invalid choice: 4"),
    (["--step-size", "-1"], "argument --step-size: expected a finite number > 0"),
    (["--step-size", "0.015", "--sample-period", "0.01"],
     "--step-size 0.015 is not an integer multiple of the sample period (--sample-period)"),
    (["--prefix", "9lives"], "argument --prefix: prefix must be a C identifier"),
    (["--out", "OUT/comp.zip"], "must end in .fmu"),
    (["--out", "OUT/my-comp.fmu"], "the file's stem (give --prefix)"),
])
def test_bad_options_name_the_argument(case: dict, tmp_path: Path, capsys, argv: list,
                                       message: str) -> None:
    from torchhys.cli.export import main

    ckpt = tmp_path / "m.ckpt"
    torch.save(lightning_ckpt(case["net"]), ckpt)
    argv = [a.replace("OUT", str(tmp_path)) for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "comp.fmu")]
    try:
        rc = main(["--ckpt", str(ckpt), "--format", "fmu", *argv])
    except SystemExit as e:
        rc = e.code
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1], err
    assert not (tmp_path / "comp.fmu").exists()


def test_fmu_flags_apply_to_the_fmu_format_only(tmp_path: Path, capsys) -> None:
    from torchhys.cli.export import main

    torch.save(trained().state_dict(), tmp_path / "sd.pt")
    rc = main(["--ckpt", str(tmp_path / "sd.pt"), "--format", "torchscript", "--out",
               str(tmp_path / "m.pt"), "--fmi", "2", "--hidden", "8",
               "--operator-kwargs", json.dumps({"a": 1.3})])
    assert rc == 2 and "--fmi applies to --format fmu only" in capsys.readouterr().err
