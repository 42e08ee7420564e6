"""The registry of model families identified on data: FAMILIES, SEARCHES and
register_family."""
import math
import subprocess
import sys

import pytest
import torch

import torchhys.registry as registry
from torchhys.registry import FAMILIES, register_family


@pytest.fixture()
def families() -> dict:
    """FAMILIES (and SEARCHES) as they were, restored after the test."""
    saved, searches = dict(FAMILIES), dict(registry.SEARCHES)
    yield FAMILIES
    FAMILIES.clear()
    FAMILIES.update(saved)
    registry.SEARCHES.clear()
    registry.SEARCHES.update(searches)


BUILTIN = ["drift", "gpi", "jiles_atherton", "pi_ls", "pi_nonneg", "plays", "preisach",
           "stop_pi"]


def test_the_registry_lists_every_family_on_first_use() -> None:
    """In a fresh interpreter, ``torchhys.registry.FAMILIES`` and ``SEARCHES`` list every
    built-in family on their first read, with nothing else imported first; ``import
    torchhys`` and the registry's import load no family module (that first read does)."""
    code = ("import sys, torchhys, torchhys.registry as r\n"
            "print(any(m.startswith('torchhys.identification') for m in sys.modules))\n"
            "print(sorted(r.FAMILIES))\n"
            "print(sorted(r.SEARCHES))\n"
            "print('torchhys.identification.specs' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    before, families, searches, after = proc.stdout.splitlines()
    assert before == "False" and after == "True"
    assert families == str(BUILTIN)
    assert searches == str(["gpi", "pi_ls", "pi_nonneg", "preisach", "stop_pi"])


@pytest.mark.slow
def test_a_family_module_imported_first_registers_every_family() -> None:
    """A family module imported on its own (which registers itself as it loads) and then a
    read of the registry: every built-in family, no error from the half-loaded module."""
    code = ("import torchhys.identification.generalized_pi\n"
            "import torchhys.registry as r\n"
            "print(sorted(r.FAMILIES))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(BUILTIN)


def test_a_user_family_named_as_a_built_in_one_is_refused_at_once(families: dict) -> None:
    import types

    with pytest.raises(ValueError, match="family name 'stop_pi' is registered already"):
        register_family("stop_pi", lambda spec: None)
    nameless = types.FunctionType((lambda spec: None).__code__, {})  # its __module__: None
    assert nameless.__module__ is None
    with pytest.raises(ValueError, match="family name 'gpi' is registered already"):
        register_family("gpi", nameless)


def test_a_registered_family_is_built_by_name(families: dict) -> None:
    def build(spec):
        return ("placeholder", spec["fit"])

    register_family("my_family_reg", build)
    assert families["my_family_reg"] is build
    assert families["my_family_reg"]({"fit": "my_family_reg"}) == ("placeholder",
                                                                    "my_family_reg")
    register_family("my_family_reg", build)  # the same builder again: a no-op
    assert families["my_family_reg"] is build
    assert registry.FAMILIES is families


def test_a_name_taken_by_another_builder_is_one_line(families: dict) -> None:
    register_family("my_family_reg", lambda spec: None)
    with pytest.raises(ValueError, match="family name 'my_family_reg' is registered "
                                         "already") as info:
        register_family("my_family_reg", lambda spec: None)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("builder", [None, 3, "fit"])
def test_a_builder_that_is_not_callable_is_one_line(families: dict, builder: object) -> None:
    with pytest.raises(TypeError, match="family 'my_family_reg': builder must be "
                                        "callable") as info:
        register_family("my_family_reg", builder)  # type: ignore[arg-type]
    assert "\n" not in str(info.value)
    assert "my_family_reg" not in families


@pytest.mark.parametrize("name", ["", None, 1])
def test_a_name_that_is_not_a_non_empty_str_is_refused(families: dict, name: object) -> None:
    with pytest.raises(ValueError, match="family name must be a non-empty str"):
        register_family(name, lambda spec: None)  # type: ignore[arg-type]


def test_a_registered_family_is_built_and_fitted_from_a_spec(families: dict) -> None:
    """``{"fit": NAME}`` of a family registered by a user builds its placeholder and fits it
    on the training data, as the built-in ones; an unknown name lists it with them."""
    import torch
    from torch import nn

    from torchhys import Backlash
    from torchhys.identification.specs import build_operators, fit_data_dependent

    def build(spec):
        n = spec.get("n", 3)

        def fit(x, y, warmup, mask=None):
            return Backlash(torch.linspace(0.1, 0.2, n) * float(x.abs().max()))

        return Backlash(torch.arange(1, n + 1) / n), fit

    register_family("my_family_reg", build)
    (op,), fitters = build_operators({"fit": "my_family_reg", "n": 2})
    assert isinstance(op, Backlash) and list(fitters) == [0]
    x = 4 * torch.sin(torch.linspace(0, 6, 50))[None]
    fit_data_dependent(nn.ModuleList([op]), fitters, x, x)
    expected = Backlash(torch.linspace(0.1, 0.2, 2) * float(x.abs().max())).state_dict()
    for key, value in op.state_dict().items():
        torch.testing.assert_close(value, expected[key].to(value.dtype))
    with pytest.raises(ValueError, match=r"no model family is called 'nope'; families: \[.*"
                                         r"'my_family_reg'.*'stop_pi'") as info:
        build_operators({"fit": "nope"})
    assert "\n" not in str(info.value)


# --- the families' searches ---------------------------------------------------------------
F64 = torch.float64


def _pi_record(sign: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Loops of a non-negative PI plant (anticlockwise) of growing and shrinking amplitude,
    times ``sign``, with a little noise: one row of 400 samples."""
    from torchhys import PrandtlIshlinskii

    t = torch.arange(400, dtype=F64)
    x = (torch.sin(2 * math.pi * t / 60) * (0.6 + 0.4 * torch.sin(2 * math.pi * t / 370)))[None]
    plant = PrandtlIshlinskii(torch.tensor([0.1, 0.3, 0.6], dtype=F64),
                              torch.tensor([1.0, 0.5, 0.25], dtype=F64), linear_weight=0.5)
    with torch.no_grad():
        y = plant(x)[0]
    return x, sign * (y + 0.01 * torch.randn(y.shape, dtype=F64,
                                              generator=torch.Generator().manual_seed(0)))


def _rmse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).square().mean().sqrt())


def test_every_family_with_a_choice_declares_its_search() -> None:
    from torchhys.identification import generalized_pi, prandtl_ishlinskii, preisach, stop_pi

    assert registry.SEARCHES == {
        "pi_ls": prandtl_ishlinskii.search_pi_ls, "pi_nonneg": prandtl_ishlinskii.search_pi_nonneg,
        "gpi": generalized_pi.search_gpi, "preisach": preisach.search_preisach,
        "stop_pi": stop_pi.search_stop_pi}


def test_a_search_registered_with_a_family_is_in_searches(families: dict) -> None:
    def search(x, y, warmup, cut):
        return None

    register_family("my_family_reg", lambda spec: None, search=search)
    assert registry.SEARCHES["my_family_reg"] is search
    with pytest.raises(TypeError, match="family 'my_family_reg2': search must be callable "
                                        "or None") as info:
        register_family("my_family_reg2", lambda spec: None, search=3)  # type: ignore[arg-type]
    assert "\n" not in str(info.value) and "my_family_reg2" not in families


@pytest.mark.slow
def test_the_pi_ls_search_is_the_best_setting_of_a_plain_loop() -> None:
    """``pi_ls``'s search (the ridges scored at once from the moments) chooses the setting
    that fitting and scoring each one in turn on the hold-out chooses, with its RMS error,
    and refits it on every sample."""
    from torchhys.identification._family_spec import PENALTIES
    from torchhys.identification.fitting import fit_prandtl_ishlinskii, play_width_grid

    x, y = _pi_record()
    warmup, cut, grid = 10, 300, {"n_widths": (2, 6), "powers": (1.0, 2.0)}
    found = registry.SEARCHES["pi_ls"](x, y, warmup, cut, **grid)
    scores = {}
    for n in grid["n_widths"]:
        for power in grid["powers"]:
            widths = play_width_grid(x, n, power=power)
            for ridge in PENALTIES:
                m = fit_prandtl_ishlinskii(x[:, :cut], y[:, :cut], widths, ridge=ridge,
                                           warmup=warmup)
                with torch.no_grad():
                    scores[n, power, ridge] = _rmse(m(x)[0][:, cut:], y[:, cut:])
    (n, power, ridge), best = min(scores.items(), key=lambda kv: kv[1])
    assert found.options == {"fit": "pi_ls", "n_widths": n, "power": power, "ridge": ridge}
    assert found.holdout == pytest.approx(best, rel=1e-6)
    whole = fit_prandtl_ishlinskii(x, y, play_width_grid(x, n, power=power), ridge=ridge,
                                   warmup=warmup)
    with torch.no_grad():
        torch.testing.assert_close(found.predict(x), whole(x)[0])


@pytest.mark.slow
def test_the_stop_pi_search_is_the_best_setting_of_a_plain_loop() -> None:
    """``stop_pi``'s search over thresholds, segments and both signs of the target (its
    ridge from the moments) against fitting and scoring each setting in turn."""
    from torchhys import fit_stop_pi
    from torchhys.identification._family_spec import PENALTIES
    from torchhys.identification.fitting import play_width_grid

    x, y = _pi_record(-1.0)
    warmup, cut = 10, 300
    grid = {"n_widths": (3,), "powers": (1.0,), "segments": (1, 2)}
    found = registry.SEARCHES["stop_pi"](x, y, warmup, cut, **grid)
    scores = {}
    for n in grid["n_widths"]:
        thresholds = play_width_grid(x[:, warmup:], n, power=1.0)
        for k in grid["segments"]:
            for sign in (1.0, -1.0):
                for ridge in PENALTIES:
                    m = fit_stop_pi(x[:, :cut], sign * y[:, :cut], thresholds, segments=k,
                                    ridge=ridge, warmup=warmup)
                    with torch.no_grad():
                        scores[n, k, sign, ridge] = _rmse(sign * m(x)[0][:, cut:], y[:, cut:])
    (n, k, sign, ridge), best = min(scores.items(), key=lambda kv: kv[1])
    assert found.options == {"fit": "stop_pi", "n_widths": n, "power": 1.0, "segments": k,
                             "sign": sign, "ridge": ridge}
    assert found.holdout == pytest.approx(best, rel=1e-6)


@pytest.mark.parametrize("family, grid", [
    ("pi_nonneg", {"n_widths": (3,), "powers": (1.0,)}),
    ("preisach", {"levels": (6,)}),
])
def test_a_search_of_the_negated_target_chooses_the_other_sign(family: str, grid: dict) -> None:
    """The non-negative families draw loops of one orientation: their searches try both signs
    of the target, so the negated record gives the same hold-out error with the other sign
    and the negated prediction (the PI plant's anticlockwise loops: sign +1, direct)."""
    x, y = _pi_record()
    plain = registry.SEARCHES[family](x, y, 10, 300, **grid)
    flipped = registry.SEARCHES[family](x, -y, 10, 300, **grid)
    assert plain.options["sign"] == 1.0 and flipped.options["sign"] == -1.0
    assert plain.options.get("direction", "direct") == "direct"
    assert {**flipped.options, "sign": 1.0} == plain.options
    assert flipped.holdout == pytest.approx(plain.holdout, rel=1e-9)
    with torch.no_grad():
        torch.testing.assert_close(flipped.predict(x), -plain.predict(x))
        assert _rmse(plain.predict(x)[:, 10:], y[:, 10:]) < 0.1 * float(y.std())


def test_the_pi_nonneg_search_inverts_where_the_input_is_the_plants_output() -> None:
    """Where the input is the PI plant's output and the target its input, the input from the
    target is the plant: the search chooses the inverse of that forward fit."""
    x, y = _pi_record()
    found = registry.SEARCHES["pi_nonneg"](y, x, 10, 300, n_widths=(3,), powers=(1.0,))
    assert found.options["direction"] == "inverse", found.options
    with torch.no_grad():
        assert _rmse(found.predict(y)[:, 10:], x[:, 10:]) < 0.1 * float(x.std())
