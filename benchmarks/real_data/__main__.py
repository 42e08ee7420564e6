"""``python -m benchmarks.real_data``: the command line of :mod:`benchmarks.real_data.cli`."""

from .cli import main

main()
