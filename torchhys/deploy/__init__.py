"""Deployment: the streaming compensator and its exporters (TorchScript, AOTInductor, C99,
ONNX, FMU)."""

import torchhys.deploy.adaptive  # noqa: F401  (StreamingCompensator(..., adapt=...) builds it)
