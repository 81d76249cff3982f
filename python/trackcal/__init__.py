"""trackcal: calibration of electromagnetic 6-DOF trackers against an optical reference.

Quaternion arrays are ordered ``x, y, z, w`` (the VRPN wire order); positions are in metres.

Correcting poses::

    cal = trackcal.Calibration.load("calib.json")
    positions, quaternions_xyzw, extrapolated = cal.correct(positions, quaternions_xyzw)

Validation, diagnosis and reports (docs/understand.md; the ``trackcal`` command)::

    from trackcal import captures, validation, report
    v = validation.validate(captures.load_poses("capture/"), cal)
    report.write_report(v, "report/")

Modules: ``captures`` (capture files), ``validation`` (Table 1, breakdowns, covariate analysis),
``figures``, ``report``, ``history`` (fit history of a work folder), ``record`` (live VRPN streams).
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
