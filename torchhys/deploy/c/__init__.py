"""Export a compensator as dependency-free C99, generated from its exported step.

:func:`to_c` builds the :class:`~torchhys.deploy.streaming.StreamingCompensator` of a model, exports
its explicit-state step with ``torch.export`` at batch 1 (static shapes) and writes C from the
graph, one small template per aten operation (:mod:`torchhys.deploy.c._templates`): every tensor a
fixed-size array, parameters and buffers ``static const`` arrays, the state a struct the
caller owns. No operator has C of its own: a new operator whose step exports with
``torch.export`` gets C without new code, or :func:`to_c` names the operation without a
template and the step it came from. So do compositions of operators, recurrent layers
(``nn.LSTM``, ``nn.GRU``, ``nn.RNN``) and MLPs (:func:`torchhys.compose.compose`): their
gates are ``linear``, ``chunk``, ``sigmoid``, ``tanh`` and elementwise templates (a layer or
RMS norm, softmax and log-softmax are templates too; an eval-mode batch norm is folded into
a per-channel scale and shift when the C is written, and one in training mode refused), the
``exp``, ``sigmoid`` and ``tanh`` of a double libm-free functions whose loops vectorize,
and a matrix product of a long inner dimension runs over blocks of output columns whose
sums stay in registers.

The generated ``PREFIX.h`` declares (C99; the files include only ``<math.h>``,
``<stdint.h>`` and ``<string.h>``; no dynamic allocation, no global mutable state, no
recursion)::

    typedef double PREFIX_real;                      (float with dtype=torch.float32)
    typedef struct { ... } PREFIX_state;              (the caller's: stack, static, PLC)
    void PREFIX_init(PREFIX_state *s);                 (fresh state, as reset())
    PREFIX_real PREFIX_step(PREFIX_state *s, PREFIX_real x);
    int64_t PREFIX_nonfinite_count(const PREFIX_state *s);
    int64_t PREFIX_out_of_range_count(const PREFIX_state *s);
    PREFIX_LOW, PREFIX_HIGH                            (the command's saturation)
    PREFIX_STATE_BYTES                                 (sizeof(PREFIX_state))

and a comment with the model, its training range, the torchhys version and the export
options. With ``adapt="rls"`` or ``"nlms"``
(:class:`~torchhys.deploy.adaptive.AdaptiveCompensator`)
the step is ``PREFIX_real PREFIX_step_adapt(PREFIX_state *s, PREFIX_real desired,
[const PREFIX_real *conditions,] PREFIX_real measured_prev, PREFIX_real applied_prev)``,
beside ``PREFIX_N_WEIGHTS``, ``void PREFIX_weights(const PREFIX_state *s, PREFIX_real *out)``
(the readout's current weights) and ``PREFIX_updates_count``, ``PREFIX_skipped_count`` and
``PREFIX_refused_count``; that source also includes ``<assert.h>``: its functions assert a
non-NULL state (compiled out with ``NDEBUG``; the static step does not test it)
(:mod:`torchhys.deploy.c._adaptive`).
The step is the TorchScript and AOTI files' step: saturation, a NaN or inf sample
held and counted, the input clamp and the direction guard. The source stops with an
``#error`` where ``__FAST_MATH__`` is defined (``-ffast-math``, ``-Ofast``: GCC, Clang);
its tests of NaN and inf read the numbers' bits and its ``exp`` takes its rounding from
bits too, so that a build that bypasses the check still holds NaN samples
(:mod:`torchhys.deploy.c._finite`). With ``-ffp-contract=off`` (the default of ``-std=c99``)
float64 results equal the TorchScript file's to about 1e-15.

The generator's parts, one concept a file: the entry (``_to_c.py``), the graph's walk
(``_graph.py``), the C primitives (``_writer.py``) and its libm-free ``exp``, ``sigmoid``
and ``tanh`` (``_libm.py``), one template per aten operation
(``_templates.py``, over ``_pointwise.py``, ``_views.py``, ``_products.py``, ``_norms.py``
and ``_indexing.py``), the tests of non-finite samples (``_finite.py``) and the two written files
(``_files.py``).
"""

from torchhys.deploy.c._to_c import DEFAULT_PREFIX, check_prefix, to_c

__all__ = ["DEFAULT_PREFIX", "check_prefix", "to_c"]
