"""The linear blocks of :mod:`torchhys.dynamics` as registered operators.

With one input a :class:`~torchhys.dynamics.TransferFunction`,
:class:`~torchhys.dynamics.TransferFunctionMatrix` or :class:`~torchhys.dynamics.StateSpace`
is an operator of the protocol; they are registered here, beside the other operators, as
``"transfer_function"``, ``"transfer_function_matrix"`` and ``"state_space"``.
"""

from torchhys.dynamics.state_space import StateSpace
from torchhys.dynamics.transfer_function import TransferFunction
from torchhys.dynamics.transfer_function_matrix import TransferFunctionMatrix
from torchhys.registry import register_operator
from torchhys.testing import Example

register_operator("transfer_function", TransferFunction, example=Example(
    # the scan of the sequence path (kernel off) rounds otherwise than the DF2T step
    lambda: TransferFunction.from_coefficients([0.2, 0.3, 0.1], [1.0, -0.5, 0.2]), atol=1e-12))

register_operator("transfer_function_matrix", TransferFunctionMatrix, example=Example(
    # one input (an operator), two outputs of their own poles; the scan of the sequence path
    # (kernel off) rounds otherwise than the DF2T step
    lambda: TransferFunctionMatrix.from_coefficients(
        [[([0.2, 0.3], [1.0, -0.5])], [([0.0, 0.4, 0.1], [1.0, 0.3, 0.2])]]),
    atol=1e-12))

register_operator("state_space", StateSpace, example=Example(
    # two states, two outputs; the scan of the sequence path (kernel off) rounds otherwise
    lambda: StateSpace.from_matrices([[0.5, 0.2], [-0.1, 0.7]], [1.0, 0.5],
                                     [[1.0, 0.0], [0.3, -0.4]], [0.2, 0.0]),
    atol=1e-12))
