"""Models whose hysteresis depends on measured operating conditions (a coil voltage, a supply
pressure, a temperature): :class:`ScheduledReadout`. A conditioned model declares
``n_conditions`` (:class:`torchhys.protocols.Conditioned`); the compensator and the exports
then take the conditions beside the input."""

from torchhys.conditions.basis import legendre_basis
from torchhys.conditions.jiles_atherton import ConditionedJilesAtherton
from torchhys.conditions.play import ConditionedBacklash
from torchhys.conditions.scheduled import ScheduledReadout

__all__ = ["ConditionedBacklash", "ConditionedJilesAtherton", "ScheduledReadout",
           "legendre_basis"]
