"""trackcal: calibration of electromagnetic 6-DOF trackers against an optical reference.

Quaternion arrays are ordered ``x, y, z, w`` (the VRPN wire order); positions are in metres.

Correcting poses::

    cal = trackcal.Calibration.load("calib.json")
    positions, quaternions_xyzw, extrapolated = cal.correct(positions, quaternions_xyzw)

Fitting a model file with the C++ engine in process (docs/python.md)::

    report = trackcal.fit("capture/", "model.yaml", folds=5)
    print(report.format()); report.save("calib.json")
    doc = trackcal.diagnose_candidates("capture/", "model.yaml")   # which effect is missing

Validation, diagnosis and reports (docs/understand.md; the ``trackcal`` command)::

    from trackcal import captures, validation, report
    v = validation.validate(captures.load_poses("capture/"), cal)
    report.write_report(v, "report/")

Modules: ``fitting`` (fit, register, pair), ``diagnosis`` (candidate effects and the verdict),
``captures`` (capture files), ``validation`` (Table 1, breakdowns, covariate analysis),
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
from trackcal.diagnosis import diagnose_candidates
from trackcal.fitting import FitReport, Pairing, Registration, fit, pair, register

__all__ = [
    "Calibration",
    "Correction",
    "FitReport",
    "Pairing",
    "Registration",
    "PolynomialCorrection",
    "TrilinearLutCorrection",
    "__version__",
    "angular_distance",
    "diagnose_candidates",
    "fit",
    "num_polynomial_terms",
    "pair",
    "polynomial_term_exponents",
    "register",
    "sha256_file",
]
