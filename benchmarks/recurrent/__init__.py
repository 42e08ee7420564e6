"""Recurrent models beside hysteresis operators: held-out accuracy and step latency.

    python -m benchmarks.recurrent [accuracy] [latency] [--quick] [--data NAME ...]
        [--rtneural DIR] [--sizes 16 32 64]

``accuracy`` (:mod:`.accuracy`): on the Bouc-Wen benchmark (``../shared/data``, the split of
benchmarks/bouc_wen_benchmark.py) and on shipped recordings (the protocols of
benchmarks/real_data, ``mr_damper_3.21V`` and ``pneumatic_oring`` by default), 8 learnable
plays + a GRU of 8 units + a linear read-out against a plain GRU (8 and 16 units) and a plain
LSTM (16 units), all plain ``nn.Module`` s trained the same way (Adam on windows, early
stopping on the validation part, the best of the seeds on validation), beside the memoryless
line and polynomial of benchmarks/real_data/baselines.py; held-out RMSE and parameters.

``latency`` (:mod:`.latency`): the generated C step of an LSTM and a GRU of 16, 32 and 64
units (:func:`torchhys.compose.compose` -> :func:`torchhys.deploy.c.to_c`) against RTNeural's
compile-time API (``--rtneural DIR`` or ``$RTNEURAL_DIR``; skipped with the reason where
absent), same flags, same run; and the composed model's (plays -> GRU -> linear) C step.
"""
