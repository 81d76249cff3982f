"""trackcal: calibration of electromagnetic 6-DOF trackers against an optical reference.

Quaternion arrays are ordered ``x, y, z, w`` (the VRPN wire order); positions are in metres.

Correcting poses::

    cal = trackcal.Calibration.load("calib.json")
    positions, quaternions_xyzw, extrapolated = cal.correct(positions, quaternions_xyzw)
    # With a physical term: how its model inverse arrived at each pose (0 converged, 1 ambiguous,
    # 2 not_converged; trackcal.correction_status_names).
    p, q, extrapolated, status = cal.correct(positions, quaternions_xyzw, return_status=True)
    trackcal.status_counts(status)   # {"converged": ..., "ambiguous": ..., "not_converged": ...}

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
    correction_status_names,
    num_polynomial_terms,
    polynomial_term_exponents,
    sha256_file,
)
from trackcal.diagnosis import diagnose_candidates
from trackcal.fitting import FitReport, Pairing, Registration, fit, pair, register


def status_counts(status) -> dict:
    """Counts of each correction status in a status array of ``correct(..., return_status=True)``:
    ``{"converged": n0, "ambiguous": n1, "not_converged": n2}`` (ValueError for unknown codes)."""
    import numpy as np
    codes = np.asarray(status).ravel()
    known = list(range(len(correction_status_names)))
    # Compared as numbers, not truncated: 1.7 counted as ambiguous and NaN failed inside bincount.
    # Element by element, so an object array of valid codes (pandas) counts too.
    values = codes.tolist()
    for c in values:
        if not (isinstance(c, (int, float)) and c in known):
            raise ValueError(f"status code {c!r}: status codes must be 0..{len(correction_status_names) - 1}")
    counts = np.bincount(np.asarray(values, dtype=np.int64), minlength=len(correction_status_names))
    return {name: int(counts[i]) for i, name in enumerate(correction_status_names)}


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
    "correction_status_names",
    "diagnose_candidates",
    "fit",
    "num_polynomial_terms",
    "pair",
    "polynomial_term_exponents",
    "register",
    "sha256_file",
    "status_counts",
]
