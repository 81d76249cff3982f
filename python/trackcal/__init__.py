"""trackcal: calibration of electromagnetic 6-DOF trackers against an optical reference.

Quaternion arrays are ordered ``x, y, z, w`` (the VRPN wire order); positions are in metres.
"""

from trackcal._core import __version__, angular_distance

__all__ = ["__version__", "angular_distance"]
