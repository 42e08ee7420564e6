"""Linear dynamic blocks, stable by construction: transfer functions and state-space models.

- :class:`TransferFunction`: a SISO transfer function ``B(z) / A(z)``.
- :class:`TransferFunctionMatrix`: a p x m matrix of SISO transfer functions,
  ``y_i = sum_j H_ij(z) x_j``, each entry with its own denominator and numerator.
- :class:`StateSpace`: ``s[t+1] = A s[t] + B x[t]``, ``y[t] = C s[t] + D x[t]``, with one
  or several inputs.

With one input they are operators of the protocol (:mod:`torchhys.operator`, registered by
:mod:`torchhys.operators.linear`): they train
inside an :class:`~torchhys.InverseHysteresisNet`, stream through the
:class:`~torchhys.deploy.streaming.StreamingCompensator` and export, with a per-sample step that
calls the same maths as the sequence path (:mod:`torchhys.functional.linear_filter`). With
several inputs (``n_inputs > 1``) the sequence path takes x (..., time, m) and the step
(``streaming_step(dtype)``) x (batch, m); such a block is not an operator of the protocol
(which feeds one input column) and :func:`~torchhys.operator.check_operator` rejects it.

Stable parametrizations (poles strictly inside a circle of radius ``r < 1`` for every value
of the parameters):

- :class:`TransferFunction`, :class:`TransferFunctionMatrix`: each denominator is a product
  of second-order sections ``1 + a1 z^-1 + a2 z^-2`` (and one first-order section for an odd
  order). Each section lies in the stability triangle scaled to radius r:
  ``c2 = tanh(alpha)``, ``c1 = (1 + c2) tanh(beta)``, ``a1 = r c1``, ``a2 = r^2 c2``; every
  real or complex pole pair of modulus below r is reached. The numerators are free.
- :class:`StateSpace`: ``A = r W / max(1, ||W||_2)``, so ``||A||_2 <= r`` (a contraction:
  spectral radius below r). Every stable system has such a realisation
  (:meth:`StateSpace.from_matrices` changes coordinates where ``||A||_2 >= 1``).

References:
    A. V. Oppenheim and R. W. Schafer, Discrete-Time Signal Processing, 3rd ed., 2010,
    Secs. 6.3-6.5 (cascade of second-order sections, transposed forms); E. I. Jury, Theory
    and Application of the z-Transform Method, 1964 (the stability triangle);
    ``scipy.signal.lfilter`` and ``scipy.signal.dlsim`` (the conventions).
"""

from torchhys.dynamics.state_space import StateSpace, StateSpaceStep
from torchhys.dynamics.transfer_function import TransferFunction, TransferFunctionStep
from torchhys.dynamics.transfer_function_matrix import (
    TransferFunctionMatrix,
    TransferFunctionMatrixStep,
)

__all__ = [
    "StateSpace",
    "StateSpaceStep",
    "TransferFunction",
    "TransferFunctionMatrix",
    "TransferFunctionMatrixStep",
    "TransferFunctionStep",
]
