"""The adaptive compensator (torchhys.deploy.adaptive): equal to the static one without
pairs, RLS against a batch ridge solution of the same regressors (computed here from the
batch operators, in float64), convergence to a known weight change, the bound, the skip and
refusal rules under adversarial pairs, the step against its sequence form, reset."""

import math

import pytest
import torch
from torch import nn

import torchhys
from torchhys import InverseHysteresisNet, PrandtlIshlinskii
from torchhys.deploy.adaptive import AdaptiveCompensator
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.functional.backlash import backlash

D = torch.float64
WIDTHS = torch.tensor([0.0, 0.4, 0.9, 1.5], dtype=D)


def pi_inverse() -> torchhys.PrandtlIshlinskiiInverse:
    pi = PrandtlIshlinskii(WIDTHS, torch.tensor([0.6, 0.3, 0.2, 0.1], dtype=D),
                           linear_weight=0.3)
    return pi.inverse()


def signal(n: int, seed: int = 0, amp: float = 2.0) -> torch.Tensor:
    """A rich bounded signal (three tones, a slow amplitude modulation), float64."""
    g = torch.Generator().manual_seed(seed)
    ph = torch.rand(3, generator=g, dtype=D) * 6.28
    t = torch.arange(n, dtype=D) / 200.0
    s = (torch.sin(2.1 * t + ph[0]) + 0.5 * torch.sin(5.3 * t + ph[1])
         + 0.3 * torch.sin(11.7 * t + ph[2]))
    return amp / 1.8 * s * (0.6 + 0.4 * torch.cos(0.37 * t))


def adaptive(model: nn.Module, **kw) -> AdaptiveCompensator:
    opts = {"limits": (-10.0, 10.0), "direction": "increasing", "input_range": (-2.5, 2.5)}
    return AdaptiveCompensator(model, **{**opts, **kw})


def identity_net() -> InverseHysteresisNet:
    """Three plays and an affine readout, fitted by least squares to a PI inverse's output."""
    ops = [torchhys.Backlash(torch.tensor([0.3, 0.8, 1.4]))]
    net = InverseHysteresisNet(ops, hidden=1, activation="identity").double()
    y = signal(3000, seed=5)
    u, _ = pi_inverse()(y)
    net.fit_normalization(y, u)
    from torchhys.selection.candidates import solve_readout
    from torchhys.selection.folds import Batch
    solve_readout(net, Batch(y[None], u[None], torch.ones(1, y.numel(), dtype=torch.bool)))
    return net


MODELS = {"pi_inverse": pi_inverse, "identity_net": identity_net,
          "tanh_net": lambda: _tanh_net()}


def _tanh_net() -> InverseHysteresisNet:
    torch.manual_seed(0)
    net = InverseHysteresisNet([torchhys.Backlash(torch.tensor([0.3, 0.8]))], hidden=6,
                               activation="tanh").double()
    y = signal(500, seed=2)
    net.fit_normalization(y, pi_inverse()(y)[0])
    return net


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("method", ["rls", "nlms"])
def test_without_pairs_the_static_compensator(name: str, method: str) -> None:
    model = MODELS[name]()
    x = signal(600, seed=1)
    kw = {"limits": (-10.0, 10.0), "direction": "increasing", "input_range": (-2.5, 2.5)}
    static = StreamingCompensator(model, **kw)(x)
    comp = adaptive(model, adapt=method)
    got = comp(x)
    assert float((got - static).abs().max()) <= 1e-12 * float(static.abs().max())
    assert torch.equal(comp.adapted_weights()[0], comp.offline_weights())
    # the readout's weights reproduce the head
    head = comp.head
    f = torch.randn(7, head_inputs(comp), dtype=D)
    assert torch.allclose((head.readout_basis(f) * head.readout_weights()).sum(1),
                          head(f)[:, 0], atol=1e-12, rtol=1e-12)


def head_inputs(comp: StreamingCompensator) -> int:
    return 1 + sum(int(s.step.n_outputs) for s in comp.slots)


def regressors(comp: AdaptiveCompensator, y: torch.Tensor) -> torch.Tensor:
    """The normalized regressors of the PI inverse's affine form on y, from the batch play
    operator (independent of the per-sample steps): [y, plays(y), 1] / scale."""
    plays = backlash(y.clamp(float(comp.in_low), float(comp.in_high)), WIDTHS_INV(comp))
    yc = y.clamp(float(comp.in_low), float(comp.in_high))
    basis = torch.cat([yc[:, None], plays, torch.ones_like(yc[:, None])], 1)
    return basis * comp.inv_scale


def WIDTHS_INV(comp: AdaptiveCompensator) -> torch.Tensor:
    return 2.0 * comp.slots[0].step.r


def test_rls_equals_batch_ridge_least_squares() -> None:
    """forgetting 1, no bound, no skip: n updates from w0 with P0 = p0 I are the ridge
    solution argmin sum (u - z w)^2 + |w - w0|^2 / p0 over the pairs after the first."""
    comp = adaptive(pi_inverse(), adapt="rls", forgetting=1.0, adapt_bound=1e9,
                    excitation=0.0, direction="none", initial_covariance=0.5)
    n = 400
    y = signal(n + 1, seed=3)
    u = 0.8 * y + 0.1 * torch.sin(torch.arange(n + 1, dtype=D) / 7.0)  # any target
    for t in range(1, n + 1):
        comp.step(y[t:t + 1], measured_prev=y[t - 1:t], applied_prev=u[t - 1:t])
    z = regressors(comp, y[:n])[1:]  # the first pair only anchors the regressors
    w0 = comp.w0.double()
    p0 = 0.5
    A = z.T @ z + torch.eye(z.shape[1], dtype=D) / p0
    b = z.T @ u[1:n] + w0 / p0
    ridge = torch.linalg.solve(A, b)
    got = comp.w0 + comp.state[2 * comp.k][0]
    assert int(comp.updates_count()) == n - 1
    assert torch.allclose(got, ridge, rtol=1e-8, atol=1e-9), (got, ridge)


@pytest.mark.parametrize("method", ["rls", "nlms"])
def test_converges_to_a_known_weight_change(method: str) -> None:
    """Pairs from an exactly affine relation with other weights: the weights reach them."""
    comp = adaptive(pi_inverse(), adapt=method, forgetting=0.995, adapt_bound=2.0,
                    excitation=0.0)
    w_true = comp.offline_weights().clone() * (1.0 + 0.3 * torch.cos(
        torch.arange(comp.m, dtype=D)))
    w_true[-1] = 0.05  # an offset
    y = signal(6000, seed=4)
    basis = regressors(comp, y) / comp.inv_scale
    u = basis @ w_true
    prior = []  # each pair's error with the weights before its update
    for t in range(1, y.numel()):
        prior.append(float(u[t - 1] - basis[t - 1] @ comp.adapted_weights()[0]))
        comp.step(y[t:t + 1], measured_prev=y[t - 1:t], applied_prev=u[t - 1:t])
    if method == "rls":  # exact data: the weights themselves
        err = (comp.adapted_weights()[0] - w_true).abs().max()
        assert float(err) < 1e-6, (comp.adapted_weights(), w_true)
    # NLMS on strongly correlated regressors converges slowly in the weights (it tracks
    # the operating point); its error before each update is what it shrinks
    late = torch.tensor(prior[-2000:], dtype=D).square().mean().sqrt()
    offline = (basis[-2001:-1] @ comp.offline_weights() - u[-2001:-1]).square().mean().sqrt()
    assert float(late) < (1e-6 if method == "rls" else 0.1) * float(offline), (late, offline)


def test_the_bound_holds_and_commands_stay_within_limits() -> None:
    comp = adaptive(pi_inverse(), adapt="rls", adapt_bound=0.1, initial_covariance=100.0)
    bound = comp.bound * comp.inv_scale
    y = signal(3000, seed=6)
    g = torch.Generator().manual_seed(1)
    for t in range(1, y.numel()):
        applied = 5.0 * y[t - 1:t] + torch.randn(1, generator=g, dtype=D)  # far off
        u = comp.step(y[t:t + 1], measured_prev=y[t - 1:t], applied_prev=applied)
        assert -10.0 <= float(u) <= 10.0
    dev = (comp.adapted_weights()[0] - comp.offline_weights()).abs()
    assert bool((dev <= bound * (1 + 1e-12)).all())
    assert float(dev.max()) > 0.5 * float(bound.max())  # it did move to the bound


@pytest.mark.parametrize("method", ["rls", "nlms"])
def test_adversarial_pairs_skip_and_count(method: str) -> None:
    comp = adaptive(pi_inverse(), adapt=method)
    y = signal(1200, seed=7)
    u = pi_inverse()(y)[0]
    bad = {100: math.nan, 101: math.inf, 102: -math.inf, 300: 1e300}
    skipped = 0
    for t in range(1, y.numel()):
        m = y[t - 1:t].clone()
        a = u[t - 1:t].clone()
        if t in bad:
            m[0] = bad[t]
            skipped += not math.isfinite(bad[t])
        if t == 200:
            a[0] = math.nan
            skipped += 1
        w_before = comp.adapted_weights().clone()
        out = comp.step(y[t:t + 1], measured_prev=m, applied_prev=a)
        assert bool(torch.isfinite(out).all())
        assert bool(torch.isfinite(comp.adapted_weights()).all())
        if t in bad and not math.isfinite(bad[t]) or t == 200:
            assert torch.equal(comp.adapted_weights(), w_before)
    comp.step(y[:1])  # no pair given: skipped too
    assert int(comp.skipped_count()) == skipped + 1
    dev = (comp.adapted_weights()[0] - comp.offline_weights()).abs()
    assert bool((dev <= comp.bound * comp.inv_scale * (1 + 1e-12)).all())


def test_an_update_against_the_direction_is_refused() -> None:
    """Pairs of a falling relation (u = -3 y) for a rising compensator: an update whose
    readout would change against the device's direction between the last update's measured
    response and this one is refused and counted; every applied one goes its way (checked
    here from the state's Z before and after); without a direction none is refused."""
    y = signal(2000, seed=8)
    for direction in ("increasing", "none"):
        comp = adaptive(pi_inverse(), adapt="rls", adapt_bound=10.0, initial_covariance=100.0,
                        direction=direction)
        m = comp.m
        for t in range(1, y.numel()):
            z_old = comp.state[-2][0].clone()
            n_old = int(comp.updates_count())
            comp.step(y[t:t + 1], measured_prev=y[t - 1:t], applied_prev=-3.0 * y[t - 1:t])
            if int(comp.updates_count()) > n_old and direction == "increasing":
                z_new, w = comp.state[-2][0], comp.w0 + comp.state[2 * comp.k][0]
                du = float(((z_new[:m] - z_old[:m]) * w).sum())
                assert du * float(z_new[m] - z_old[m]) >= 0.0, t
        if direction == "increasing":
            assert int(comp.refused_count()) > 0
        else:
            assert int(comp.refused_count()) == 0


@pytest.mark.parametrize("method", ["rls", "nlms"])
def test_step_equals_sequence_and_explicit_forms(method: str) -> None:
    comp = adaptive(identity_net(), adapt=method)
    n = 500
    x, y = signal(n, seed=9), 1.1 * signal(n, seed=10)
    a = 0.9 * signal(n, seed=11)
    y[50:55] = math.nan
    seq = comp(x[None], measured=y[None], applied=a[None])[0]
    state = comp.initial_state(1)
    steps = []
    for t in range(n):
        ut = comp.step(x[t:t + 1], measured_prev=y[t:t + 1], applied_prev=a[t:t + 1])
        ue, state = comp.step_explicit(x[t:t + 1], state, measured_prev=y[t:t + 1],
                                       applied_prev=a[t:t + 1])
        assert torch.equal(ut, ue)
        steps.append(ut)
    assert torch.equal(torch.cat(steps), seq)
    for s, e in zip(comp.state, state, strict=True):
        assert torch.equal(s, e)
    assert int(comp.updates_count()) > 0


def test_reset_returns_to_the_offline_weights_bit_for_bit() -> None:
    comp = adaptive(pi_inverse(), adapt="rls")
    fresh = adaptive(pi_inverse(), adapt="rls")
    y = signal(400, seed=12)
    for t in range(1, 400):
        comp.step(y[t:t + 1], measured_prev=y[t - 1:t], applied_prev=1.2 * y[t - 1:t])
    assert not torch.equal(comp.adapted_weights()[0], comp.offline_weights())
    comp.reset()
    assert torch.equal(comp.adapted_weights()[0], comp.offline_weights())
    x = signal(100, seed=13)
    for t in range(100):
        assert torch.equal(comp.step(x[t:t + 1]), fresh.step(x[t:t + 1]))


def test_scripted_equals_eager() -> None:
    comp = adaptive(pi_inverse(), adapt="rls")
    scripted = torch.jit.script(adaptive(pi_inverse(), adapt="rls"))
    y = signal(300, seed=14)
    for t in range(1, 300):
        pair = {"measured_prev": y[t - 1:t], "applied_prev": 0.7 * y[t - 1:t]}
        assert torch.equal(comp.step(y[t:t + 1], **pair), scripted.step(y[t:t + 1], None,
                                                                         pair["measured_prev"],
                                                                         pair["applied_prev"]))
    assert torch.equal(comp.adapted_weights(), scripted.adapted_weights())


@pytest.mark.parametrize(("kw", "name"), [
    ({"forgetting": 0.0}, "forgetting"), ({"forgetting": 1.5}, "forgetting"),
    ({"forgetting": math.nan}, "forgetting"), ({"adapt_bound": -1.0}, "adapt_bound"),
    ({"dead_zone": -0.1}, "dead_zone"), ({"excitation": -1.0}, "excitation"),
    ({"nlms_step": 2.0}, "nlms_step"), ({"initial_covariance": 0.0}, "initial_covariance"),
    ({"adapt": "kalman"}, "adapt"),
])
def test_bad_options_name_the_argument(kw: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name) as err:
        adaptive(pi_inverse(), **kw)
    assert "\n" not in str(err.value)


class _NoReadout(nn.Module):
    """A deployable whose head is not affine in weights of its own."""

    def __init__(self) -> None:
        super().__init__()
        self.inner = pi_inverse()

    def streaming_steps(self, dtype: torch.dtype) -> list:
        return self.inner.streaming_steps(dtype)

    def streaming_head(self, dtype: torch.dtype) -> nn.Module:
        return self.inner.streaming_head(dtype)


def test_a_model_without_an_affine_readout_is_refused() -> None:
    with pytest.raises(ValueError, match="no affine readout") as err:
        adaptive(_NoReadout())
    assert "\n" not in str(err.value)


def test_a_pair_of_the_wrong_shape_is_refused() -> None:
    comp = adaptive(pi_inverse())
    with pytest.raises(ValueError, match="measured_prev must have x's shape"):
        comp.step(torch.zeros(1, dtype=D), measured_prev=torch.zeros(2, dtype=D),
                  applied_prev=torch.zeros(1, dtype=D))
    with pytest.raises(ValueError, match="applied_prev"):
        comp(torch.zeros(1, 5, dtype=D), measured=torch.zeros(1, 5, dtype=D),
             applied=torch.zeros(5, dtype=D))
    assert int(comp.n_steps) == 0  # nothing stepped


def conditioned_net() -> InverseHysteresisNet:
    """Plays and a readout scheduled on one condition (degree 1), least squares."""
    from torchhys.selection.candidates import solve_readout
    from torchhys.selection.folds import Batch

    y = torch.stack([signal(800, seed=s) for s in range(3)])
    c = torch.linspace(0.0, 1.0, 3, dtype=D)[:, None, None].expand(3, 800, 1).contiguous()
    u = pi_inverse()(y)[0] * (1.0 + 0.3 * c[..., 0])
    net = InverseHysteresisNet([torchhys.Backlash(torch.tensor([0.3, 0.9]))], 1,
                               activation="identity", n_conditions=1,
                               condition_degree=1).double()
    net.fit_normalization(y, u, conditions=c)
    solve_readout(net, Batch(y, u, torch.ones_like(y, dtype=torch.bool), c))
    return net


@pytest.mark.parametrize("method", ["rls", "nlms"])
def test_a_conditioned_network_adapts_with_its_conditions(method: str) -> None:
    """The conditioned readout (features times the conditions' basis) adapts: without pairs
    the static compensator's commands; with pairs of a changed gain it tracks them better;
    the scripted module steps equally."""
    net = conditioned_net()
    kw = {"direction": "increasing", "input_range": (-2.5, 2.5), "limits": (-10.0, 10.0)}
    x = signal(600, seed=20)
    c = torch.full((600, 1), 0.5, dtype=D)
    comp = AdaptiveCompensator(net, adapt=method, **kw)
    static = StreamingCompensator(net, **kw)(x, c)
    assert float((comp(x, c) - static).abs().max()) < 1e-12
    scripted = torch.jit.script(AdaptiveCompensator(net, adapt=method, **kw))
    u = 1.4 * pi_inverse()(x)[0]  # the device now needs 40 % more command
    for t in range(1, 600):
        args = (x[t:t + 1], c[t:t + 1], x[t - 1:t], u[t - 1:t])
        assert torch.equal(comp.step(*args), scripted.step(*args))
    assert int(comp.updates_count()) > 100
    err_static = (static[300:] - u[300:]).square().mean()
    adapted = comp(x, c, measured=torch.cat([x[:1], x[:-1]]), applied=torch.cat([u[:1], u[:-1]]))
    assert float((adapted[300:] - u[300:]).square().mean()) < 0.3 * float(err_static)


def test_the_streaming_compensator_with_adapt_is_the_adaptive_one() -> None:
    import copy

    kw = {"limits": (-10.0, 10.0), "direction": "increasing", "input_range": (-2.5, 2.5)}
    comp = StreamingCompensator(pi_inverse(), adapt="nlms", nlms_step=0.3, **kw)
    assert type(comp) is AdaptiveCompensator and not comp.rls and comp.nlms_step == 0.3
    assert type(StreamingCompensator(pi_inverse(), adapt="none", **kw)) is StreamingCompensator
    twin = copy.deepcopy(comp)
    y = signal(200, seed=21)
    for t in range(1, 200):
        pair = {"measured_prev": y[t - 1:t], "applied_prev": 1.3 * y[t - 1:t]}
        assert torch.equal(comp.step(y[t:t + 1], **pair), twin.step(y[t:t + 1], **pair))
    with pytest.raises(ValueError, match="adapt must be one of"):
        StreamingCompensator(pi_inverse(), adapt="lms", **kw)
