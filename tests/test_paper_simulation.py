"""The paper's simulated experiments, against an independent loop."""

from __future__ import annotations

import math

import numpy as np
from _helpers import play_reference

from torchhys.plants import fig6_simulation, paper_simulation


def test_paper_simulation_section_5_2():
    t, x, h = paper_simulation()
    assert t.shape == x.shape == h.shape == (2514,)
    tn = np.arange(0.0, 8 * math.pi, 0.01)
    xn = 4 * np.sin(0.5 * tn) + 2 * np.sin(3 * tn)
    np.testing.assert_allclose(x.numpy(), xn, atol=1e-6)
    widths = np.linspace(1 / 6, 15 / 6, 15)
    hn = play_reference(xn[None], widths).sum(-1)[0]
    np.testing.assert_allclose(h.numpy(), hn, rtol=1e-6, atol=1e-4)
    # the loop is closed after the first period of the slow sine and stays bounded
    assert float(h.abs().max()) < 15 * 6


def test_fig6_simulation():
    t, x, h = fig6_simulation(dt=0.02)
    tn = np.arange(0.0, 8 * math.pi, 0.02)
    xn = 2 * np.sin(3 * tn) + 3 * np.sin(0.5 * tn)
    hn = play_reference(xn[None], np.linspace(0.5, 5, 10)).sum(-1)[0]
    np.testing.assert_allclose(h.numpy(), hn, rtol=1e-6, atol=1e-4)
