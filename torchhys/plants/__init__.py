"""Simulated hysteretic plants."""

__all__: list[str] = []
