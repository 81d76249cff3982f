import math

import trackcal


def test_version_matches_project():
    assert trackcal.__version__ == "0.1.0"


def test_angular_distance_sign_invariant():
    q = [0.1, 0.2, 0.3, 0.9]
    minus_q = [-v for v in q]
    assert trackcal.angular_distance(q, minus_q) < 1e-7
    half = math.sin(0.25)
    assert math.isclose(trackcal.angular_distance([0, 0, 0, 1], [0, 0, half, math.cos(0.25)]), 0.5,
                        rel_tol=1e-12)
