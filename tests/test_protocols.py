"""The declared roles of a model (torchhys.protocols): the built-ins play them, and a model
that lacks a member is refused where it is given, with one line naming the argument and
every member it lacks."""
from __future__ import annotations

import pytest
import torch
from torch import nn

from torchhys import InverseHysteresisNet, PrandtlIshlinskii
from torchhys.deploy.c import to_c
from torchhys.deploy.export import to_aoti, to_torchscript
from torchhys.deploy.export_onnx import to_onnx
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.protocols import (
    Deployable,
    Network,
    check_deployable,
    check_network,
    missing_members,
)
from torchhys.step import OperatorStep, StateBlock, check_step


class NoHead(nn.Module):
    """A network with its operators, features and normalization but no head, and one of
    the two deployable members."""

    def __init__(self) -> None:
        super().__init__()
        self.operators = nn.ModuleList()
        self.linear = nn.Linear(1, 1)

    def features(self, x, state=None, *, target=None, segment_a=None):
        return x.unsqueeze(-1), []

    def fit_normalization(self, x, y, *, mask=None) -> None:
        pass

    def streaming_steps(self, dtype):
        return []


def test_the_built_in_models_declare_their_roles() -> None:
    net = InverseHysteresisNet("eiho", hidden=3)
    inverse = PrandtlIshlinskii([0.5, 1.0], linear_weight=1.0).inverse()
    assert isinstance(net, Network) and isinstance(net, Deployable)
    assert {Network, Deployable} <= set(InverseHysteresisNet.__mro__)  # declared
    assert isinstance(inverse, Deployable) and not isinstance(inverse, Network)
    assert missing_members(net, Network) == [] and missing_members(net, Deployable) == []
    assert check_network(net) is net and check_deployable(inverse) is inverse


def test_the_members_are_read_from_the_declaration() -> None:
    assert missing_members(object(), Network) == ["operators", "features", "head",
                                                  "fit_normalization"]
    assert missing_members(object(), Deployable) == ["streaming_steps", "streaming_head"]
    assert missing_members(NoHead(), Network) == ["head"]
    assert not isinstance(NoHead(), Network) and not isinstance(NoHead(), Deployable)


EXPORTS = {"compensator": lambda m, tmp: StreamingCompensator(m),
           "torchscript": lambda m, tmp: to_torchscript(m, tmp / "c.pt"),
           "aoti": lambda m, tmp: to_aoti(m, tmp / "c.pt2"),
           "onnx": lambda m, tmp: to_onnx(m, tmp / "c.onnx"),
           "c": lambda m, tmp: to_c(m, tmp)}


@pytest.mark.parametrize("entry", list(EXPORTS))
def test_the_compensator_and_the_exports_name_the_missing_member(entry: str, tmp_path) -> None:
    if entry == "onnx":
        for module in ("onnx", "onnxscript"):
            pytest.importorskip(module)
    with pytest.raises(TypeError, match=r"^model must be an nn\.Module with the members of "
                       r"torchhys\.protocols\.Deployable .*got NoHead: it has no "
                       r"streaming_head$"):
        EXPORTS[entry](NoHead(), tmp_path)
    with pytest.raises(TypeError, match=r"^model .*got str: it is no nn\.Module; it has no "
                       r"streaming_steps, streaming_head$"):
        EXPORTS[entry]("eiho", tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_the_training_module_names_the_missing_member() -> None:
    pytest.importorskip("lightning")
    from torchhys.training.module import InverseHysteresisModule

    with pytest.raises(TypeError, match=r"^net must be an nn\.Module with the members of "
                       r"torchhys\.protocols\.Network .*got NoHead: it has no head$"):
        InverseHysteresisModule(NoHead())
    net = InverseHysteresisNet("eiho", hidden=3)
    assert InverseHysteresisModule(net).net is net


class _Step(OperatorStep):
    def __init__(self, spec: object) -> None:
        super().__init__()
        self.n_outputs = 1
        if spec is not None:
            self.state_spec = spec

    def forward(self, x, state):
        return x, state


def test_a_step_outside_the_step_protocol_is_named() -> None:
    assert check_step(_Step([StateBlock("y", 1)])).n_outputs == 1
    with pytest.raises(TypeError, match=r"^streaming step 0 \(_Step\) has no state_spec"):
        check_step(_Step(None), "streaming step 0")
    with pytest.raises(TypeError, match=r"state_spec must be a list of StateBlock"):
        check_step(_Step(["y"]))
    with pytest.raises(TypeError, match=r"^step must be a torchhys\.step\.OperatorStep, "
                       r"got Linear"):
        check_step(nn.Linear(1, 1))

    class Model(nn.Module):
        def streaming_steps(self, dtype: torch.dtype) -> list:
            return [_Step(None)]

        def streaming_head(self, dtype: torch.dtype) -> nn.Module:
            return nn.Identity()

    with pytest.raises(TypeError, match=r"^streaming step 0 \(_Step\) has no state_spec"):
        StreamingCompensator(Model(), limits=(-1, 1))
