"""The registry of model families identified on data: FAMILIES and register_family."""
import pytest

import torchhys.registry as registry
from torchhys.registry import FAMILIES, register_family


@pytest.fixture()
def families() -> dict:
    """FAMILIES as it was, restored after the test."""
    saved = dict(FAMILIES)
    yield FAMILIES
    FAMILIES.clear()
    FAMILIES.update(saved)


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
