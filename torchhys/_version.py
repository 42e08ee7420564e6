"""The package's version, in a module of its own: the exporters write it into their files
without importing the whole package, and the build reads it from here (pyproject.toml)."""

__version__ = "0.1.0"
