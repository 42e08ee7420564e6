"""The parts of the FMU exporter :func:`torchhys.deploy.export_fmu.to_fmu` (a co-simulation
FMU, FMI 2.0 or 3.0, whose binary is the C99 step).

``to_fmu`` writes ``NAME.fmu``: the model description, ``sources/`` (the C step of
:func:`torchhys.deploy.c.to_c` and the FMI wrapper) and the binary compiled here
(``binaries/linux64`` or ``binaries/x86_64-linux``); ``check_fmu`` reads one back,
through FMPy's validation where ``torchhys[fmu]`` is installed. ``docs/deployment.md``
("FMU") describes the variables, the timing and the import into other tools.

The parts, one concept a file: the variables' table
(``_variables.py``), the model and build descriptions (``_xml.py``), the C shared by both
wrappers (``_core.py``: the FMU's state, the samples of a communication step, the serialized
state) and the wrappers of FMI 2.0 (``_fmi2.py``, ``_fmi2_unsupported.py``) and FMI 3.0
(``_fmi3.py``, ``_fmi3_unsupported.py``), written from the standards' function signatures.
"""
