"""The FMU exporter's public path: :func:`to_fmu` (a co-simulation FMU, FMI 2.0 or 3.0, whose
binary is the generated C99 step) and :func:`check_fmu`, from :mod:`torchhys.deploy.fmu`."""

from torchhys.deploy.fmu import check_fmu, to_fmu

__all__ = ["check_fmu", "to_fmu"]
