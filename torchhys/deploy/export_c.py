"""The earlier path of :mod:`torchhys.deploy.c` (the C99 generator), kept so that
``from torchhys.deploy.export_c import to_c`` still works: the same objects, under their
one home :mod:`torchhys.deploy.c`."""

from torchhys.deploy.c import DEFAULT_PREFIX, check_prefix, to_c

__all__ = ["DEFAULT_PREFIX", "check_prefix", "to_c"]
