"""make_operator, the one resolver of operator specs: a registered name, a dict
``{"name": ..., **options}`` or an operator; its errors; networks and cascades resolve their
specs through it."""

from __future__ import annotations

import pytest
import torch

from torchhys import EIHO, Backlash, Cascade, InverseHysteresisNet
from torchhys.dynamics import TransferFunction
from torchhys.registry import OPERATORS, make_operator

WIDTHS = [0.1, 0.4]


def test_a_name_a_dict_and_an_operator() -> None:
    by_name = make_operator("backlash", widths=torch.tensor(WIDTHS))
    by_dict = make_operator({"name": "backlash", "widths": torch.tensor(WIDTHS)})
    by_both = make_operator({"name": "backlash"}, widths=torch.tensor(WIDTHS))
    for op in (by_name, by_dict, by_both):
        assert type(op) is Backlash
        torch.testing.assert_close(op.get_widths(), torch.tensor(WIDTHS), rtol=0, atol=0)
    given = EIHO(a=2.0)
    assert make_operator(given) is given
    assert type(make_operator("eiho")) is OPERATORS["eiho"]  # the default options


def test_a_dict_may_hold_specs_of_its_parts() -> None:
    op = make_operator({"name": "cascade", "first": "transfer_function",
                        "second": {"name": "backlash", "widths": torch.tensor(WIDTHS)}})
    assert isinstance(op, Cascade)
    assert [type(s) for s in op.stages] == [TransferFunction, Backlash]


UNKNOWN = r"no operator is registered as {}; registered names: \[.*'backlash', .*'eiho'.*\]$"


@pytest.mark.parametrize("spec, options, error, match", [
    ("no_such_op", {}, ValueError, "^spec: " + UNKNOWN.format("'no_such_op'")),
    ({"name": "eihoo"}, {}, ValueError, "^spec: " + UNKNOWN.format("'eihoo'")),
    ({"name": 3}, {}, ValueError, "^spec: " + UNKNOWN.format("3")),
    ({"a": 1.0}, {}, ValueError, r"^spec: a spec dict needs a 'name' \(a registered operator\), "
                                 r"got \{'a': 1.0\}$"),
    ({"fit": "preisach"}, {}, ValueError,
     r"^spec: a spec dict needs a 'name' .*\{'fit': \.\.\.\} is a model family"),
    ({"name": "eiho", "a": 1.0}, {"a": 2.0}, ValueError,
     r"^spec: option\(s\) \['a'\] given in the spec and as keywords$"),
    ("eiho", {"b": 1.0}, ValueError, r"^spec 'eiho': .*unexpected keyword argument 'b'$"),
    ("eiho", {"rule": "newest"}, ValueError, r"^rule must be one of .*'newest'"),
    (EIHO(), {"a": 2.0}, TypeError,
     r"^spec: options \['a'\] apply to an operator given by name, not to a EIHO instance$"),
    (torch.nn.Linear(1, 1), {}, TypeError,
     r"^spec must be a torchhys.HysteresisOperator .* got Linear \(it has no streaming_step"),
    (3, {}, TypeError, r"^spec must be a registered operator name, a dict \{'name': NAME, "
                       r"\*\*options\} or a HysteresisOperator, got int 3$"),
    (EIHO, {}, TypeError, r"^spec must be a registered operator name, .* got ABCMeta"),
])
def test_errors_name_the_argument_and_the_known_names(spec, options, error, match) -> None:
    with pytest.raises(error, match=match) as raised:
        make_operator(spec, argument="spec", **options)
    assert "\n" not in str(raised.value)


def test_the_argument_defaults_to_operator() -> None:
    with pytest.raises(ValueError, match=r"^operator: no operator is registered as 'x'"):
        make_operator("x")


def test_a_network_resolves_its_specs() -> None:
    net = InverseHysteresisNet(["eiho", {"name": "backlash", "widths": torch.tensor(WIDTHS)},
                                EIHO(a=2.0)], hidden=3, operator_kwargs={"rule": "dominant"})
    assert [type(op) for op in net.operators] == [EIHO, Backlash, EIHO]
    assert net.operators[0].rule == "dominant"  # operator_kwargs: the names alone
    assert net.hidden.in_features == 1 + 1 + 2 + 1
    with pytest.raises(ValueError, match=r"^operator\[1\]: no operator is registered as 'x'"):
        InverseHysteresisNet(["eiho", "x"])
    with pytest.raises(ValueError, match=r"^operator: no operator is registered as 'x'"):
        InverseHysteresisNet("x")
    with pytest.raises(TypeError, match=r"^operator\[0\] must be a registered operator name"):
        InverseHysteresisNet([1.5])


def test_a_cascade_resolves_its_parts() -> None:
    op = Cascade("transfer_function", {"name": "backlash", "widths": torch.tensor(WIDTHS)})
    assert [type(s) for s in op.stages] == [TransferFunction, Backlash]
    with pytest.raises(ValueError, match=r"^operator 1 of the cascade: a spec dict needs a "
                                         r"'name'"):
        Cascade("transfer_function", {"a": 1.0})
    with pytest.raises(ValueError, match=r"^operator 0 of the cascade: no operator is "
                                         r"registered as 'x'; registered names: \["):
        Cascade("x", "eiho")
