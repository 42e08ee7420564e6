"""The earlier path of :mod:`torchhys.deploy.c` (the C99 generator), kept so that
``from torchhys.deploy.export_c import to_c`` still works, with a :class:`DeprecationWarning`:
the same objects, from their one home :mod:`torchhys.deploy.c`."""

from torchhys._deprecated import moved as _moved

__getattr__ = _moved(
    __name__, dict.fromkeys(("DEFAULT_PREFIX", "check_prefix", "to_c"), "torchhys.deploy.c"))
