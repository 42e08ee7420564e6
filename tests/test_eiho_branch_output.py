"""The re-based (branch-local) output of the branch operators: ``output="branch"``.

``f - f(x_e)`` with ``x_e`` the committed anchor: against the float64 loop, chunked equals
whole, its relation to the level output, boundedness, gradients, bad input.
"""

from __future__ import annotations

import pytest
import torch
from _branch_reference import ref_branch
from _helpers import batch, random_walk, run_chunked, smooth_input

from torchhys import EIHO, InverseHysteresisNet, ZhaoTanOperator
from torchhys.functional import eiho, turning_points, zhao_tan


def f64(values: list[float]) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("threshold", [0.0, 1.0])
@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_eiho_branch_matches_loop(seed: int, threshold: float, rule: str) -> None:
    x = random_walk(seed, quantize=seed % 2 == 0)
    a = torch.tensor([1.3, 0.7], dtype=torch.float64)
    f, _ = eiho(x, a, rule=rule, threshold=threshold, max_depth=5, output="branch")
    ref = ref_branch(x.tolist(), a_up=1.3, a_down=0.7, threshold=threshold, rule=rule, depth=5,
                     branch=True)
    torch.testing.assert_close(f, f64(ref), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("threshold", [0.0, 1.0])
@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_zhao_tan_branch_matches_loop(threshold: float, rule: str) -> None:
    x = random_walk(1, quantize=False)
    f, _ = zhao_tan(x, rule=rule, threshold=threshold, max_depth=6, output="branch")
    ref = ref_branch(x.tolist(), kind="zhao_tan", threshold=threshold, rule=rule, depth=6,
                     branch=True)
    torch.testing.assert_close(f, f64(ref), rtol=1e-10, atol=1e-10)


def test_hand_example() -> None:
    x = f64([0.0, 1.0, 4.0, 3.0, 0.0, 2.0])
    f, _ = eiho(x, 2.0, output="branch")
    # level: [0, 2, 4, 2, 0, 2 sqrt 2]; anchors 0 (f 0), then 4 (f 4), then 0 (f 0)
    expected = f64([0, 2, 4, -2, -4, 2 * 2**0.5])
    torch.testing.assert_close(f, expected)


@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_branch_is_level_minus_anchor_level_and_bounded(rule: str) -> None:
    # a drifting input with many minor loops: the level drifts, the branch value stays
    # within a sqrt(span) of the input
    t = torch.linspace(0, 60, 3000, dtype=torch.float64)
    x = torch.sin(t) + 0.4 * torch.sin(3.7 * t) + 0.02 * t
    level, _ = eiho(x, 1.0, rule=rule)
    branch, _ = eiho(x, 1.0, rule=rule, output="branch")
    bound = float(x.max() - x.min()) ** 0.5
    assert float(branch.abs().max()) <= bound + 1e-9
    # level - branch is the anchor's level: 0 from the start, then piecewise constant,
    # changing only when the anchor changes (a confirmed turning point, or a closed loop)
    diff = level - branch
    assert float(diff[:5].abs().max()) == 0.0
    changes = int((diff.diff().abs() > 1e-12).sum())
    assert 0 < changes <= 2 * int(turning_points(x).sum()) + 1


@pytest.mark.parametrize("rule", ["recent", "dominant"])
@pytest.mark.parametrize("threshold", [0.0, 0.75])
@pytest.mark.parametrize("sizes", [[1], [7, 1, 30]])
def test_chunked_equals_whole(rule: str, threshold: float, sizes: list[int]) -> None:
    x = batch()
    for op in (
        EIHO(a=(1.5, 0.5), rule=rule, threshold=threshold, max_depth=6, output="branch"),
        ZhaoTanOperator(rule=rule, threshold=threshold, scale=2.0, output="branch"),
    ):
        op = op.double()
        whole, _ = op(x)
        torch.testing.assert_close(run_chunked(op, x, sizes), whole, rtol=1e-12, atol=1e-12)


def test_batch_consistency() -> None:
    x = batch()
    op = EIHO(a="learnable", rule="dominant", threshold=0.5, output="branch").double()
    whole, _ = op(x)
    rows = torch.stack([op(row)[0] for row in x])
    torch.testing.assert_close(whole, rows, rtol=1e-12, atol=1e-12)


def test_network_with_branch_operators_streams() -> None:
    torch.manual_seed(0)
    x = batch()
    ops = [EIHO(a=0.8, rule="recent", output="branch"),
           ZhaoTanOperator(rule="dominant", output="branch")]
    net = InverseHysteresisNet(ops, hidden=8).double()
    net.fit_normalization(x, torch.tanh(x))
    whole, _ = net(x)
    torch.testing.assert_close(run_chunked(net, x, [1, 9]), whole, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_gradcheck(rule: str) -> None:
    x = smooth_input().requires_grad_()
    a = torch.tensor([1.2, 0.8], dtype=torch.float64, requires_grad=True)
    x0 = x.detach()[0] - 0.1  # anchor below the first sample: away from the sqrt kink

    def fn(x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return eiho(torch.cat([x0.reshape(1), x]), a, rule=rule, output="branch")[0][1:]

    assert torch.autograd.gradcheck(fn, (x, a), eps=1e-7, atol=1e-6)
    assert torch.autograd.gradcheck(
        lambda x: zhao_tan(x, rule=rule, output="branch")[0], (x,), eps=1e-7
    )


def test_default_is_level() -> None:
    x = random_walk(2)
    torch.testing.assert_close(eiho(x, 1.1)[0], eiho(x, 1.1, output="level")[0])
    assert EIHO().output == "level" and ZhaoTanOperator().output == "level"
    assert "output='branch'" in repr(EIHO(output="branch"))


@pytest.mark.parametrize("bad", ["Branch", "", "relative", None])
def test_bad_output(bad: object) -> None:
    x = random_walk(0, T=20)
    with pytest.raises(ValueError, match="output must be one of"):
        eiho(x, 1.0, output=bad)
    with pytest.raises(ValueError, match="output must be one of"):
        zhao_tan(x, output=bad)
    with pytest.raises(ValueError, match="output must be one of"):
        EIHO(output=bad)
    with pytest.raises(ValueError, match="output must be one of"):
        ZhaoTanOperator(output=bad)
