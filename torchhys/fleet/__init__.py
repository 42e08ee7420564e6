"""Identify a fleet of devices at once, locally or on a Dask cluster, and flag the device
that does not fit: :func:`identify_fleet` (``torchhys fleet``; docs/fleet.md).

Needs the ``fleet`` extra (Dask ``distributed``: ``pip install "torchhys[fleet]"``) and the
``train`` extra (each device is a ``torchhys fit`` run)."""

from torchhys.fleet.cluster import ClusterError
from torchhys.fleet.devices import Device, find_devices
from torchhys.fleet.report import flag_outliers
from torchhys.fleet.run import FleetResult, identify_fleet

__all__ = ["ClusterError", "Device", "FleetResult", "find_devices", "flag_outliers",
           "identify_fleet"]
