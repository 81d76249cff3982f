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


def test_angular_distance_refuses_a_quaternion_that_is_no_rotation():
    """A zero quaternion was "0 rad from" every rotation (Eigen's normalized() leaves it zero), and
    a quaternion of 3 values was a TypeError listing pybind11 signatures."""
    import pytest
    for bad in ([0, 0, 0, 0], [math.nan, 0, 0, 1], [math.inf, 0, 0, 1]):
        with pytest.raises(ValueError, match=r"a_xyzw must be a finite, non-zero quaternion"):
            trackcal.angular_distance(bad, [0, 0, 0, 1])
        with pytest.raises(ValueError, match=r"b_xyzw must be a finite, non-zero quaternion"):
            trackcal.angular_distance([0, 0, 0, 1], bad)
    with pytest.raises(ValueError, match=r"a_xyzw must have shape \(4,\) \(x, y, z, w\), got \(3,\)"):
        trackcal.angular_distance([0, 0, 1], [0, 0, 0, 1])
    # A quaternion of another norm is the same rotation (normalised).
    assert trackcal.angular_distance([0, 0, 0, 2], [0, 0, 0, 1]) == 0.0


def test_angular_distance_of_a_quaternion_of_extreme_norm_is_its_rotation():
    """Any finite non-zero quaternion is its normalised rotation. The norm of (0, 0, 0, 1e300)
    overflowed to inf, so it normalised to zero and came out 0 rad from every rotation (pi from
    (1, 0, 0, 0) was 0.0); the norm of (0, 0, 0, 1e-300) underflowed to 0 and it was refused as a
    zero quaternion."""
    for scale in (1e300, 1e-300, 1e200):
        q = [0.0, 0.0, 0.0, scale]
        assert math.isclose(trackcal.angular_distance(q, [1, 0, 0, 0]), math.pi, rel_tol=1e-12)
        assert trackcal.angular_distance([1, 0, 0, 0], q) == trackcal.angular_distance([1, 0, 0, 0], [0, 0, 0, 1])
        assert trackcal.angular_distance(q, [0, 0, 0, 1]) == 0.0


def test_doc_examples_that_import_define_every_name_they_use():
    """A ```python block of docs/ that has import lines is a complete example to paste into a
    script, so every name it reads must be imported or assigned in it (docs/understand.md's
    validate_recording example called trackcal.Calibration after only `from trackcal import
    validation`: NameError). Blocks without imports are fragments of the text around them."""
    import ast
    import builtins
    import pathlib
    import re
    docs = pathlib.Path(__file__).resolve().parents[2] / "docs"
    checked = 0
    for md in sorted(docs.glob("*.md")):
        for block in re.findall(r"```python\n(.*?)```", md.read_text(), flags=re.S):
            tree = ast.parse(block)
            if not any(isinstance(n, (ast.Import, ast.ImportFrom)) for n in ast.walk(tree)):
                continue
            defined = set(dir(builtins))
            for n in ast.walk(tree):
                if isinstance(n, ast.Import):
                    defined |= {a.asname or a.name.split(".")[0] for a in n.names}
                elif isinstance(n, ast.ImportFrom):
                    defined |= {a.asname or a.name for a in n.names}
                elif isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store):
                    defined.add(n.id)
                elif isinstance(n, (ast.FunctionDef, ast.ClassDef)):
                    defined.add(n.name)
                elif isinstance(n, ast.arg):
                    defined.add(n.arg)
            used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
            assert used <= defined, f"{md.name}: example uses {sorted(used - defined)} without defining them:\n{block}"
            checked += 1
    assert checked >= 2
