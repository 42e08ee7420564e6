"""Deployment: the streaming compensator and its exporters (TorchScript, AOTInductor, C99,
ONNX)."""
