"""Export a compensator as a co-simulation FMU (FMI 2.0 or 3.0) whose binary is the C99 step.

See :func:`to_fmu`."""

from torchhys.deploy.fmu._to_fmu import check_fmu, to_fmu

__all__ = ["check_fmu", "to_fmu"]
