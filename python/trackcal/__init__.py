"""trackcal: calibration of electromagnetic 6-DOF trackers against an optical reference.

Quaternion arrays are ordered ``x, y, z, w`` (the VRPN wire order); positions are in metres.

Correcting poses::

    cal = trackcal.Calibration.load("calib.json")
    positions, quaternions_xyzw, extrapolated = cal.correct(positions, quaternions_xyzw)
"""

from trackcal._core import (
    Calibration,
    Correction,
    PolynomialCorrection,
    TrilinearLutCorrection,
    __version__,
    angular_distance,
    num_polynomial_terms,
    polynomial_term_exponents,
    sha256_file,
)

__all__ = [
    "Calibration",
    "Correction",
    "PolynomialCorrection",
    "TrilinearLutCorrection",
    "__version__",
    "angular_distance",
    "num_polynomial_terms",
    "polynomial_term_exponents",
    "sha256_file",
]
