"""A compensator as dependency-free C99, generated from its exported step: :func:`to_c`.

The generator's parts, one concept a file: the entry and the graph's walk (``_to_c.py``),
the C primitives (``_writer.py``), one template per aten operation (``_templates.py``, over
``_pointwise.py``, ``_views.py``, ``_products.py`` and ``_indexing.py``), the tests of
non-finite samples (``_finite.py``) and the two written files (``_files.py``).
"""

from torchhys.deploy.c._to_c import DEFAULT_PREFIX, check_prefix, to_c

__all__ = ["DEFAULT_PREFIX", "check_prefix", "to_c"]
