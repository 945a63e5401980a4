"""LiDAR from the twin's scene (the paper's future work: "multi-modal information (RGB,
LiDAR, etc.)").

* :class:`LidarSettings`: a rotating multi-beam sensor (channels, vertical field of view,
  horizontal resolution, rate, range, noise, dropout);
* :class:`Caster`: casts its sweeps into the ray tracer's Mitsuba scene with the moving
  bodies in it;
* :class:`Lidar` (``lidar``): LiDARs on UEs, a point cloud per sweep on ``3D.lidar.<UE_Id>``.
"""

from caviar_plugins.lidar.plugin import Lidar
from caviar_plugins.lidar.sensor import COLUMNS, Caster, LidarSettings, Sweep

__all__ = ["COLUMNS", "Caster", "Lidar", "LidarSettings", "Sweep"]
