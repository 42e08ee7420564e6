"""torchhys.compose: a user's module streams as it computes. The state layout and start, a
leaf called twice, submodules, copies and state dicts, training through the Composed, the
recorded ranges. The composed step against the module, chunked == one call and gradcheck
are torchhys.testing.check_composed's checks (tests/test_conformance.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _compose_models import MODELS, make, signal

import torchhys
from torchhys.compose import Composed, ComposedStartStep, ComposedStep, compose

LAYOUTS = {
    "backlash_lstm": (ComposedStep, [("bl.plays", 1), ("lstm.h", 8), ("lstm.c", 8)]),
    "parallel_gru": (ComposedStep, [("gru.h", 6), ("pi.plays", 3)]),
    "filter_eiho_gru": (ComposedStartStep, [("tf.filter", 2), ("eiho.turning", 4),
                                            ("eiho.level", 1), ("gru.h", 10)]),
}


@pytest.mark.parametrize("name", MODELS)
def test_state_layouts(name):
    """The composed step's kind and its state blocks (names and sizes, in graph order); its
    values against the module: torchhys.testing.check_composed (tests/test_conformance.py)."""
    model = make(name)
    composed = compose(model)
    step = composed.composed_step(torch.float64)
    kind, layout = LAYOUTS[name]
    assert type(step) is kind
    assert [(b.name, b.size) for b in step.state_spec] == layout
    x = signal()
    torch.testing.assert_close(composed(x), model(x), rtol=0, atol=0)  # forward is the module


def test_a_leaf_after_a_layer_starts_from_its_own_input():
    """The EIHO after the filter starts from the filter's first output (as the module's
    sequence path does), not from x0: the custom start of ComposedStartStep."""
    model = make("filter_eiho_gru")
    step = compose(model).composed_step(torch.float64)
    x = signal()
    x0 = x[:, :1]
    start = step.initial_state(x0)
    names = [b.name for b in step.state_spec]
    tf_step = model.tf.streaming_step(torch.float64)
    v0, _ = tf_step(x0, tf_step.initial_state(x0))
    eiho_start = model.eiho.streaming_step(torch.float64).initial_state(v0)
    torch.testing.assert_close(start[names.index("eiho.turning")], eiho_start[0])
    assert not torch.allclose(start[names.index("eiho.turning")][:, :1], x0)


def test_a_leaf_fed_by_the_input_keeps_its_affine_start():
    """An anchored operator on x itself needs no custom start: its blocks keep from_sample."""

    class EIHOLSTM(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.eiho = torchhys.EIHO()
            self.lstm = torch.nn.LSTM(1, 4, batch_first=True)

        def forward(self, x):
            return self.lstm(self.eiho(x)[0].unsqueeze(-1))[0].sum(-1)

    torch.manual_seed(0)
    model = EIHOLSTM().double()
    step = compose(model).composed_step(torch.float64)
    assert type(step) is ComposedStep
    assert step.state_spec[0].name == "eiho.turning"
    assert step.state_spec[0].columns("from_sample") == [1.0, 1.0, 0.0, 1.0]
    x = signal()
    torch.testing.assert_close(step.run(x)[..., 0], model(x).detach(), rtol=0, atol=1e-12)


def test_a_composed_trains_as_the_module_and_streams_its_new_weights():
    model = make("backlash_lstm")
    x = signal()
    y = torch.sin(2.0 * x)
    composed = compose(model, x=x, y=y)
    assert {p for p in composed.parameters()} == set(model.parameters())
    opt = torch.optim.Adam(composed.parameters(), lr=0.02)
    losses = []
    for _ in range(30):
        opt.zero_grad()
        loss = (composed(x) - y).square().mean()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0]
    step = composed.streaming_steps(torch.float64)[0]
    torch.testing.assert_close(step.run(x)[..., 0], model(x).detach(), rtol=0, atol=1e-12)


def test_recorded_ranges_are_the_datas():
    model = make("parallel_gru")
    x = signal()
    y = model(x).detach() + 0.1 * x
    composed = Composed(model, x=x, y=y)
    xs, ys = x.numpy().ravel(), y.numpy().ravel()
    assert float(composed.in_min) == xs.min() and float(composed.in_max) == xs.max()
    assert float(composed.out_min) == ys.min() and float(composed.out_max) == ys.max()
    assert math.isclose(float(composed.trend), np.corrcoef(xs, ys)[0, 1], rel_tol=1e-12)
    # without data: nothing recorded
    bare = compose(make("parallel_gru"))
    assert all(math.isnan(float(getattr(bare, n)))
               for n in ("in_min", "in_max", "out_min", "out_max", "trend"))


def test_compose_leaves_the_module_as_it_was():
    model = make("backlash_lstm")
    model.train()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    compose(model)
    assert model.training
    after = model.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)


class _Encoder(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.rnn = torch.nn.RNN(2, 3, batch_first=True, nonlinearity="relu")

    def forward(self, f):
        return self.rnn(f)[0]


class _Twice(torch.nn.Module):
    """One operator called on two signals (two states), and a recurrent layer inside a
    submodule of the user's."""

    def __init__(self):
        super().__init__()
        self.bl = torchhys.Backlash(torch.tensor([0.25]))
        self.enc = _Encoder()
        self.lin = torch.nn.Linear(3, 1)

    def forward(self, x):
        a = self.bl(x)[0]
        b = self.bl(-2.0 * x)[0]
        return self.lin(self.enc(torch.cat([a, b], -1))).squeeze(-1)


def test_a_leaf_called_twice_has_two_states_and_submodules_are_traced_through():
    torch.manual_seed(0)
    model = _Twice().double()
    step = compose(model).composed_step(torch.float64)
    assert [b.name for b in step.state_spec] == ["bl.plays", "bl_1.plays", "enc_rnn.h"]
    x = signal()
    torch.testing.assert_close(step.run(x)[..., 0], model(x).detach(), rtol=0, atol=1e-12)


def test_copies_pickles_and_state_dicts_stream_the_same():
    import copy
    import io

    model = make("filter_eiho_gru")
    x = signal()
    with torch.no_grad():
        y = model(x)
    composed = compose(model, x=x, y=y)
    buffer = io.BytesIO()
    torch.save(composed, buffer)
    buffer.seek(0)
    loaded = torch.load(buffer, weights_only=False)
    other = compose(make("filter_eiho_gru", seed=5))
    other.load_state_dict(composed.state_dict())
    for twin in (copy.deepcopy(composed), loaded, other):
        assert twin.module is not model
        assert float(twin.out_max) == float(y.max())
        step = twin.composed_step(torch.float64)
        torch.testing.assert_close(step.run(x)[..., 0], y, rtol=0, atol=1e-12)


class _StateSpaceMix(torch.nn.Module):
    """A two-input state-space layer (torchhys.dynamics.StateSpace) on [x, play(x)], a layer
    norm and dropout (eval: identity) before the readout."""

    def __init__(self):
        super().__init__()
        self.bl = torchhys.Backlash(torch.tensor([0.2]))
        self.ss = torchhys.dynamics.StateSpace(3, 2, n_inputs=2)
        self.norm = torch.nn.LayerNorm(2)
        self.drop = torch.nn.Dropout(0.3)
        self.lin = torch.nn.Linear(2, 1)

    def forward(self, x):
        s = self.ss(torch.cat([x.unsqueeze(-1), self.bl(x)[0]], -1))[0]
        return self.lin(self.drop(self.norm(s))).squeeze(-1)


def test_a_multi_input_state_space_layer_and_normalization():
    torch.manual_seed(0)
    model = _StateSpaceMix().double()
    composed = compose(model)
    assert model.training  # compose ran the check in eval mode and left the mode as it was
    step = composed.composed_step(torch.float64)
    assert [(b.name, b.size) for b in step.state_spec] == [("bl.plays", 1), ("ss.state", 3)]
    x = signal()
    model.eval()
    torch.testing.assert_close(step.run(x)[..., 0], model(x).detach(), rtol=0, atol=1e-12)
