"""The translation of an exported torch step into CasADi ``SX`` expressions, for
:mod:`torchhys.deploy.export_casadi` (the public entry): the symbolic tensors
(``_values.py``), one translation per aten operation (``_ops.py`` over ``_pointwise.py``
and ``_indexing.py``) and the graph's walk (``_walk.py``). Importing it does not import
casadi."""
