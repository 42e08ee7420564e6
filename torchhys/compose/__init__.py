"""Compose anything, deploy anything: a user's ``nn.Module`` of hysteresis operators,
recurrent layers (``nn.LSTM``, ``nn.GRU``, ``nn.RNN``) and elementwise maths as one
deployable model (``docs/composing.md``).

- :func:`compose` / :class:`Composed`: the module, traced and checked, as a
  :class:`~torchhys.protocols.Deployable` (the streaming compensator and every export take
  it); its per-sample step is a :class:`ComposedStep`.
- :class:`LSTMStep`, :class:`GRUStep`, :class:`RNNStep` (:func:`recurrent_step`): the steps
  of torch's trained recurrent layers, with a published state layout
  (:mod:`torchhys.compose.recurrent`); :class:`StatelessStep` (:func:`stateless_step`):
  ``nn.Linear`` and elementwise modules as steps.
"""

from torchhys.compose.composed import Composed, LastFeature, compose
from torchhys.compose.graph import ComposedStartStep, ComposedStep
from torchhys.compose.recurrent import GRUStep, LSTMStep, RNNStep, recurrent_step
from torchhys.compose.stateless import StatelessStep, stateless_step

__all__ = [
    "Composed",
    "ComposedStartStep",
    "ComposedStep",
    "GRUStep",
    "LSTMStep",
    "LastFeature",
    "RNNStep",
    "StatelessStep",
    "compose",
    "recurrent_step",
    "stateless_step",
]
