"""Pure tensor functions: the functional core of torchhys."""

__all__: list[str] = []
