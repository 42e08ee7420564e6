"""``python -m benchmarks.recurrent``: see the package docstring."""

from .cli import main

main()
