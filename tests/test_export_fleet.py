"""``torchhys export --fleet`` (torchhys/cli/export_fleet.py, torchhys/deploy/export_fleet.py):
a fleet folder of four identified devices (checkpoints written as ``torchhys fleet`` writes
them: ``ROOT/fleet_0/<device>/logs/version_0/checkpoints/last.ckpt`` and ``fleet.csv``; one
failed device) exported as one shared C step compiled with the system compiler and run with
each device's ``NAME_params`` over a record with NaN, inf and samples out of the range,
against each device's own C file (bit for bit) and the eager compensator (1e-12); one file
per device for onnx, torchscript and fmu; the fallback to one pair of C files a device where
one device chose another structure; the sizes sharing saves; bad input."""

from __future__ import annotations

import csv
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from _export_helpers import CC, FLAGS, FLOAT64_RTOL, NO_CC, gap, record

from torchhys import InverseHysteresisNet
from torchhys.cli.export import main
from torchhys.deploy.export import load_torchscript
from torchhys.deploy.export_fleet import CHECKPOINT, export_fleet, read_fleet
from torchhys.deploy.streaming import StreamingCompensator

needs_cc = pytest.mark.skipif(CC is None, reason=NO_CC)
COLUMNS = ("device", "status", "candidate", "family", "ratio", "width", "gain", "fit_s",
           "outlier", "outlier_reason", "reason", "run_dir", "config")
"""torchhys.fleet.report.COLUMNS (this file does not import the fleet: it needs Dask)."""
DEVICES = {"unit0": (0.50, 1.00, 1.3), "unit1": (0.55, 0.95, 1.1), "unit-2": (0.45, 1.05, 1.6),
           "3rd": (0.52, 1.02, 1.3)}
"""Device -> (output gain, input amplitude, EIHO's a): other weights, normalisation,
saturation and operator parameter per device; "unit-2" and "3rd" are no C identifiers."""


def _net(seed: int, gain: float, amp: float, a: float, hidden: int = 8) -> InverseHysteresisNet:
    torch.manual_seed(seed)
    kwargs = {"a": a, "rule": "dominant", "threshold": 0.1}
    net = InverseHysteresisNet("eiho", hidden, operator_kwargs=kwargs).double()
    x = 3 * amp * torch.sin(torch.linspace(0, 20, 400, dtype=torch.float64))
    net.fit_normalization(x, gain * x)
    net.hp = {"operator": "eiho", "hidden": hidden, "activation": "sigmoid",
              "operator_kwargs": kwargs}  # the checkpoint's hyper_parameters
    return net


def _save(run: Path, net: InverseHysteresisNet) -> None:
    (run / CHECKPOINT).parent.mkdir(parents=True)
    state = {f"net.{k}": v for k, v in net.state_dict().items()}
    torch.save({"state_dict": state, "hyper_parameters": net.hp, "epoch": 3}, run / CHECKPOINT)


def _fleet(root: Path, nets: dict[str, InverseHysteresisNet]) -> Path:
    """A fleet folder of ``nets`` and one failed device ("garbled"), as torchhys fleet
    writes it."""
    folder = root / "fleet_0"
    folder.mkdir(parents=True)
    rows = []
    for name, net in nets.items():
        _save(folder / name, net)
        rows.append({"device": name, "status": "ok", "family": "eiho",
                     "run_dir": str(folder / name)})
    rows.append({"device": "garbled", "status": "failed", "run_dir": str(folder / "garbled"),
                 "reason": "torchhys fit: error: could not convert string to float: 'a'"})
    with (folder / "fleet.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    return folder


@pytest.fixture(scope="module")
def nets() -> dict[str, InverseHysteresisNet]:
    return {name: _net(k, *p) for k, (name, p) in enumerate(DEVICES.items())}


@pytest.fixture(scope="module")
def fleet(tmp_path_factory, nets) -> Path:
    return _fleet(tmp_path_factory.mktemp("fleet"), nets)


@pytest.fixture(scope="module")
def pair(tmp_path_factory, nets) -> Path:
    """A fleet of two of the devices (the per-format and error tests: quicker)."""
    return _fleet(tmp_path_factory.mktemp("pair"), {n: nets[n] for n in PAIR})


PAIR = ("unit0", "unit-2")


@pytest.fixture(scope="module")
def signal() -> np.ndarray:
    return record(-3.0, 3.0, n=1500)


def _export(*argv: str) -> tuple[int, str, str]:
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(list(argv))
        except SystemExit as stop:
            rc = int(stop.code)
    return rc, out.getvalue(), err.getvalue()


SHARED_DRIVER = r"""
#include <stdio.h>
#include "fl.h"
/* each device in turn over the samples of stdin (binary doubles): its commands, binary */
int main(void)
{
    static double x[100000];
    long n = 0, i;
    int d;
    while (n < 100000 && fread(&x[n], sizeof x[0], 1, stdin) == 1) ++n;
    for (d = 0; d < fl_N_DEVICES; ++d) {
        fl_state s;
        fl_init(&s);
        for (i = 0; i < n; ++i) {
            double u = (double)fl_step(&s, &fl_params_table[d], (fl_real)x[i]);
            fwrite(&u, sizeof u, 1, stdout);
        }
        fprintf(stderr, "%s %ld\n", fl_device_names[d], (long)fl_nonfinite_count(&s));
    }
    return 0;
}
"""

ONE_DRIVER = r"""
#include <stdio.h>
#include "NAME.h"
int main(void)
{
    NAME_state s;
    double x;
    NAME_init(&s);
    while (fread(&x, sizeof x, 1, stdin) == 1) {
        double u = (double)NAME_step(&s, (NAME_real)x);
        fwrite(&u, sizeof u, 1, stdout);
    }
    return 0;
}
"""


def _run(folder: Path, driver: str, sources: list[Path], x: np.ndarray, name: str
         ) -> tuple[np.ndarray, str]:
    (folder / f"{name}.c").write_text(driver)
    exe = folder / name
    done = subprocess.run([CC, *FLAGS, "-I", str(folder), "-o", str(exe), str(folder / f"{name}.c"),
                           *map(str, sources), "-lm"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    run = subprocess.run([str(exe)], input=x.astype(np.float64).tobytes(), capture_output=True,
                         check=True)
    return np.frombuffer(run.stdout, dtype=np.float64), run.stderr.decode()


@pytest.fixture(scope="module")
def shared(fleet, tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("shared")
    rc, text, err = _export("--fleet", str(fleet), "--format", "c", "--out", str(out),
                            "--prefix", "fl")
    assert rc == 0, err
    return out, text


@pytest.fixture(scope="module")
def separate(fleet, tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("separate")
    rc, text, err = _export("--fleet", str(fleet), "--format", "c", "--out", str(out),
                            "--prefix", "fl", "--no-shared")
    assert rc == 0, err
    return out, text


def test_the_fleet_folder_lists_its_devices_and_the_failed_one(fleet) -> None:
    devices = read_fleet(fleet)
    assert list(devices.checkpoints) == list(DEVICES)
    assert list(devices.skipped) == ["garbled"]
    assert devices.skipped["garbled"].startswith("torchhys fit: error:")


def test_one_shared_step_and_a_table_of_params(shared) -> None:
    out, text = shared
    assert sorted(p.name for p in out.iterdir()) == ["fl.c", "fl.h", "fl_params.c"]
    assert "one C step shared by 4 devices" in text
    assert "skipped 1 device(s): garbled (torchhys fit: error:" in text
    header, source = (out / "fl.h").read_text(), (out / "fl.c").read_text()
    assert "fl_real fl_step(fl_state *s, const fl_params *p, fl_real x);" in header
    assert "#define fl_DEVICE_unit_2 2" in header and "#define fl_DEVICE_d3rd 3" in header
    assert "static const" in source and "p->k" in source  # common tables once, the rest in p
    params = (out / "fl_params.c").read_text()
    assert "const fl_params fl_params_table[fl_N_DEVICES]" in params
    assert params.count("/* unit") == 3 and '"unit-2"' in params


@needs_cc
def test_the_shared_step_equals_each_devices_own_c_and_the_eager_model(
        shared, separate, nets, signal) -> None:
    out, _ = shared
    got, err = _run(out, SHARED_DRIVER, [out / "fl.c", out / "fl_params.c"], signal, "fleet")
    got = got.reshape(len(DEVICES), len(signal))
    counts = [line.split() for line in err.split("\n") if line]
    assert [name for name, _ in counts] == list(DEVICES)
    sep, _ = separate
    for k, (name, net) in enumerate(nets.items()):
        ident = {"unit-2": "unit_2", "3rd": "d3rd"}.get(name, name)
        prefix = f"fl_{ident}"
        own, _ = _run(sep, ONE_DRIVER.replace("NAME", prefix), [sep / f"{prefix}.c"], signal,
                      f"run_{ident}")
        assert np.array_equal(got[k], own), name  # one generator, one order of operations
        eager = StreamingCompensator(net)(torch.tensor(signal)).numpy()
        assert gap(got[k], eager) <= FLOAT64_RTOL, (name, gap(got[k], eager))
        assert int(counts[k][1]) == int(np.isnan(signal).sum() + np.isinf(signal).sum())
    # the devices differ: their params are read, not one device's constants
    assert min(gap(got[0], got[k]) for k in range(1, len(DEVICES))) > 1e-3


def _object_sizes(sources: list[Path]) -> tuple[int, int]:
    """(source bytes, text + data + bss bytes of ``cc -O2 -c`` objects, by ``size``)."""
    total = 0
    for src in sources:
        obj = src.with_suffix(".o")
        subprocess.run([CC, "-std=c99", "-O2", "-c", "-I", str(src.parent), "-o", str(obj),
                        str(src)], check=True)
        fields = subprocess.run(["size", str(obj)], capture_output=True, text=True,
                                check=True).stdout.split("\n")[1].split()
        total += sum(int(f) for f in fields[:3])
    return sum(s.stat().st_size for s in sources), total


def sharing_saves(shared: Path, separate: Path, n: int = len(DEVICES)) -> str:
    """The bytes of the shared step and its params (``shared``: ``fl.c``, ``fl_params.c``)
    against one C file a device (``separate``: ``fl_*.c``) for ``n`` devices."""
    one = _object_sizes([shared / "fl.c", shared / "fl_params.c"])
    per = _object_sizes(sorted(separate.glob("fl_*.c")))
    step = _object_sizes([shared / "fl.c"])
    return (f"{n} devices: source {per[0]} B per device files, {one[0]} B shared; "
            f"objects {per[1]} B against {one[1]} B (the step {step[1]} B, once)")


@needs_cc
@pytest.mark.skipif(not __import__("shutil").which("size"), reason="no size (binutils)")
def test_sharing_saves_code(shared, separate, capsys) -> None:
    text = sharing_saves(shared[0], separate[0])
    with capsys.disabled():
        print("\n" + text)
    nums = [int(w) for w in text.replace(",", " ").split() if w.isdigit()]
    assert nums[1] > nums[2] and nums[3] > nums[4]


def test_a_device_of_another_structure_gives_one_pair_a_device(nets, tmp_path) -> None:
    mixed = {n: nets[n] for n in PAIR}
    mixed["odd"] = _net(7, 0.5, 1.0, 1.3, hidden=6)
    folder = _fleet(tmp_path / "runs", mixed)
    out = tmp_path / "c"
    rc, text, _ = _export("--fleet", str(folder), "--format", "c", "--out", str(out))
    assert rc == 0
    assert "not a shared step: device 'odd' differs from 'unit0' in" in text
    assert sorted(p.name for p in out.iterdir()) == sorted(
        f"torchhys_comp_{i}.{e}" for i in ("unit0", "unit_2", "odd")
        for e in "ch")
    rc, _, err = _export("--fleet", str(folder), "--format", "c", "--out", str(tmp_path / "d"),
                         "--shared")
    assert rc == 2 and "shared: device 'odd' differs from 'unit0'" in err.strip()
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("fmt", ["onnx", "torchscript"])
def test_onnx_and_torchscript_write_one_file_a_device(pair, nets, tmp_path, fmt) -> None:
    if fmt == "onnx":
        pytest.importorskip("onnxruntime", reason="the onnx extra (pip install 'torchhys[onnx]')")
    from torchhys.deploy.export_onnx import load_onnx

    suffix = {"onnx": ".onnx", "torchscript": ".pt"}[fmt]
    y = torch.tensor(record(-3.0, 3.0, n=300))
    out = tmp_path / fmt
    rc, text, err = _export("--fleet", str(pair), "--format", fmt, "--out", str(out))
    assert rc == 0, err
    assert f"one file for each of {len(PAIR)} devices" in text and "skipped 1" in text
    assert sorted(p.name for p in out.iterdir()) == sorted(n + suffix for n in PAIR)
    for name in PAIR:
        expected = StreamingCompensator(nets[name])(y)
        if fmt == "onnx":
            stepper = load_onnx(out / f"{name}.onnx")
            got = torch.stack([torch.as_tensor(stepper.step(v.reshape(1)))[0] for v in y])
        else:
            got = load_torchscript(out / f"{name}.pt")(y)
        assert gap(got, expected) <= FLOAT64_RTOL, (fmt, name)


@needs_cc
def test_fmu_writes_one_file_a_device_named_by_it(pair, tmp_path) -> None:
    out = tmp_path / "fmu"
    rc, _, err = _export("--fleet", str(pair), "--format", "fmu", "--out", str(out),
                         "--prefix", "fl")
    assert rc == 0, err
    assert sorted(p.name for p in out.iterdir()) == sorted(n + ".fmu" for n in PAIR)
    with zipfile.ZipFile(out / "unit-2.fmu") as z:
        assert 'modelIdentifier="fl_unit_2"' in z.read("modelDescription.xml").decode()


@needs_cc
def test_devices_of_equal_constants_share_every_table_and_p_is_unread(nets, tmp_path) -> None:
    net = nets["unit0"]
    done = export_fleet({"a": net, "b": net}, tmp_path, prefix="fl", shared=True)
    assert done.shared and [p.name for p in done.files] == ["fl.h", "fl.c", "fl_params.c"]
    source = (tmp_path / "fl.c").read_text()
    assert "p->" not in source and "(void)p;" in source
    for name in ("fl.c", "fl_params.c"):  # -Wextra: an unused parameter would be an error
        done = subprocess.run([CC, *FLAGS, "-c", "-I", str(tmp_path), "-o",
                               str(tmp_path / f"{name}.o"), str(tmp_path / name)],
                              capture_output=True, text=True)
        assert done.returncode == 0, done.stderr


def test_the_library_refuses_shared_for_other_formats(nets, tmp_path) -> None:
    with pytest.raises(ValueError, match="shared applies to format 'c' only"):
        export_fleet(nets, tmp_path, format="onnx", shared=True)
    with pytest.raises(ValueError, match="format must be one of c, onnx, torchscript, fmu"):
        export_fleet(nets, tmp_path, format="aoti")


@pytest.mark.parametrize(("extra", "message"), [
    (["--format", "aoti"], "--format aoti: --fleet exports c, onnx, torchscript, fmu"),
    (["--format", "onnx", "--shared"], "--shared applies to --format c only, not onnx"),
    (["--format", "c", "--adapt", "rls"], "--adapt applies to one --ckpt, not --fleet"),
    (["--format", "c", "--ckpt", "m.ckpt"], "--fleet and --ckpt exclude each other"),
    (["--format", "onnx", "--prefix", "x"], "--prefix applies to --format c or fmu"),
    (["--format", "c", "--fmi", "3"], "--fmi applies to --format fmu only"),
])
def test_bad_options_are_one_line_naming_them(pair, tmp_path, extra, message) -> None:
    rc, _, err = _export("--fleet", str(pair), "--out", str(tmp_path / "o"), *extra)
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err


def test_the_devices_plugin_modules_are_imported(pair, tmp_path) -> None:
    """--import applies to --fleet as to one --ckpt (a fleet of a plugin's operators)."""
    rc, _, err = _export("--fleet", str(pair), "--format", "c", "--out", str(tmp_path / "o"),
                         "--import", "torchhys_no_such_plugin")
    assert rc == 2 and "torchhys_no_such_plugin" in err and len(err.strip().splitlines()) == 1
    (tmp_path / "plugin_seen.py").write_text(
        "from pathlib import Path\nPath(__file__).with_suffix('.seen').write_text('x')\n")
    rc, _, err = _export("--fleet", str(pair), "--format", "c", "--out", str(tmp_path / "p"),
                         "--import-path", str(tmp_path), "--import", "plugin_seen")
    assert rc == 0, err
    assert (tmp_path / "plugin_seen.seen").exists()


def test_a_folder_without_fleet_csv_and_existing_files(pair, tmp_path) -> None:
    rc, _, err = _export("--fleet", str(tmp_path), "--format", "c", "--out", str(tmp_path))
    assert rc == 2 and f"--fleet {tmp_path}: no fleet.csv" in err
    rc, _, err = _export("--fleet", str(tmp_path / "nope"), "--format", "c", "--out",
                         str(tmp_path))
    assert rc == 2 and "no such folder" in err
    rc, _, err = _export("--shared", "--ckpt", "m.ckpt", "--format", "c", "--out", str(tmp_path))
    assert rc == 2 and "--shared applies to --fleet only" in err
    out = tmp_path / "twice"
    assert _export("--fleet", str(pair), "--format", "torchscript", "--out", str(out))[0] == 0
    rc, _, err = _export("--fleet", str(pair), "--format", "torchscript", "--out", str(out))
    assert rc == 2 and "exists; pass overwrite=True (--force)" in err
    assert _export("--fleet", str(pair), "--format", "torchscript", "--out", str(out),
                   "--force")[0] == 0


REAL = """model:
  select:
    - operator: [{fit: stop_pi, n_widths: 8, power: 2.0, segments: 2}]
  select_cv: 2
"""
"""Over configs/measured.yaml: one candidate (every device chooses one structure)."""


@pytest.mark.slow
@needs_cc
def test_a_real_fleet_exports_one_shared_step(tmp_path, signal) -> None:
    """``torchhys fleet`` of three simulated Bouc-Wen devices (a local Dask cluster), then
    ``torchhys export --fleet``: the shared step of each device equals its own C file."""
    pytest.importorskip("distributed")
    from torchhys.fleet import identify_fleet
    from torchhys.plants import bouc_wen
    from torchhys.signals import multisine, time_grid, to_range

    devs = tmp_path / "devices"
    devs.mkdir()
    t = time_grid(dt=0.01, t_end=20.0, dtype=torch.float64)
    u = to_range(multisine(t, band=(0.2, 3.0), n_tones=8, seed=0), -6.0, 6.0)
    for k, (a, g) in enumerate([(0.5, 1.0), (0.52, 0.98), (0.48, 1.03)]):
        y = g * bouc_wen(u, t, A=a)
        np.savetxt(devs / f"dev{k}.csv", torch.stack([t, u, y], 1).numpy(), delimiter=",",
                   header="time,command,response", comments="", fmt="%.6f")
    (tmp_path / "one.yaml").write_text(REAL)
    root = Path(__file__).resolve().parents[1]
    result = identify_fleet(str(devs / "*.csv"), root=tmp_path / "runs", workers=2,
                            config=[root / "configs" / "measured.yaml", tmp_path / "one.yaml"],
                            say=lambda s: None)
    assert result.failed == []
    out, sep = tmp_path / "c", tmp_path / "sep"
    rc, text, err = _export("--fleet", str(result.folder), "--format", "c", "--out", str(out),
                            "--prefix", "fl", "--shared")
    assert rc == 0 and "one C step shared by 3 devices" in text, err
    assert _export("--fleet", str(result.folder), "--format", "c", "--out", str(sep),
                   "--prefix", "fl", "--no-shared")[0] == 0
    x = record(-5.0, 5.0, n=1500)
    got, _ = _run(out, SHARED_DRIVER, [out / "fl.c", out / "fl_params.c"], x, "fleet")
    got = got.reshape(3, len(x))
    for k in range(3):
        own, _ = _run(sep, ONE_DRIVER.replace("NAME", f"fl_dev{k}"), [sep / f"fl_dev{k}.c"],
                      x, f"run{k}")
        assert np.array_equal(got[k], own), k
    assert gap(got[0], got[1]) > 1e-4
