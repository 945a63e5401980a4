"""UAV energy (the paper's future work: "energy consumption tracking for the UAV").

* :class:`RotaryWing`: the propulsion power of a rotary-wing UAV (Zeng, Xu and Zhang,
  IEEE TWC 2019, with climb and acceleration), its maximum-endurance and maximum-range
  speeds;
* :class:`Battery`: capacity, initial state of charge and the reserve a mission keeps;
* :class:`UavEnergy` (``uav-energy``): every UAV's power, energy and battery per step on
  ``uav.energy``, and when it must fly home.
"""

from caviar_plugins.energy.plugin import UavEnergy
from caviar_plugins.energy.rotary_wing import Battery, RotaryWing

__all__ = ["Battery", "RotaryWing", "UavEnergy"]
