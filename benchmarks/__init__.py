"""Benchmarks and the scripts that draw the docs' figures. The real-data benchmark
(:mod:`benchmarks.real_data`) and the scripts that import it run from the repository's root
as modules: ``python -m benchmarks.real_data``."""
