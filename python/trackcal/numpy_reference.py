"""Plain-numpy implementations of the runtime corrections, written from the documented conventions
(docs/calibration-file.md) independently of the C++ code.

They are the cross-check of the native path in the tests and the baselines of the benchmarks
(bench/bench_python_batch.py; ``fit_polynomial_lstsq`` for the fit engine's lone polynomial). They do
not apply the calibrated volume.
"""

from __future__ import annotations

import numpy as np


def term_exponents(degree: int) -> np.ndarray:
    """(R, 3) powers of x, y, z in the canonical order: graded by total degree, then descending
    power of x, then descending power of y."""
    terms = []
    for d in range(degree + 1):
        for a in range(d, -1, -1):
            for b in range(d - a, -1, -1):
                terms.append((a, b, d - a - b))
    return np.array(terms, dtype=np.int64)


def monomials(degree: int, u: np.ndarray) -> np.ndarray:
    """(N, R) monomials of normalised positions u (N, 3), from per-axis power tables."""
    exps = term_exponents(degree)
    powers = np.ones((degree + 1,) + u.shape, dtype=np.float64)  # powers[k] = u**k
    for k in range(1, degree + 1):
        powers[k] = powers[k - 1] * u
    return powers[exps[:, 0], :, 0].T * powers[exps[:, 1], :, 1].T * powers[exps[:, 2], :, 2].T


def quaternion_multiply_xyzw(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (N, 4) x, y, z, w arrays."""
    ax, ay, az, aw = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
    bx, by, bz, bw = b[:, 0], b[:, 1], b[:, 2], b[:, 3]
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=1,
    )


def quaternion_from_vector_part(v: np.ndarray) -> np.ndarray:
    """(N, 4) x, y, z, w unit quaternions with vector part v and non-negative scalar part; |v| >= 1
    maps to the 180 degree rotation about v (as core/pose.h does)."""
    n2 = np.sum(v * v, axis=1)
    inside = n2 < 1.0
    w = np.sqrt(np.where(inside, 1.0 - n2, 0.0))
    scale = np.where(inside, 1.0, 1.0 / np.sqrt(np.where(inside, 1.0, n2)))
    return np.concatenate([v * scale[:, None], w[:, None]], axis=1)


def correct_polynomial(
    degree: int,
    position_coefficients: np.ndarray,
    orientation_coefficients: np.ndarray,
    input_offset,
    input_scale,
    positions: np.ndarray,
    quaternions_xyzw: np.ndarray,
):
    """p + e_p(u), q_e(u) * q with u = (p - input_offset) / input_scale (eq. 4, 7)."""
    u = (positions - np.asarray(input_offset)) / np.asarray(input_scale)
    m = monomials(degree, u)
    e_p = m @ position_coefficients
    v = m @ orientation_coefficients
    return positions + e_p, quaternion_multiply_xyzw(quaternion_from_vector_part(v), quaternions_xyzw)


def orientation_error_vectors(q_reference: np.ndarray, q_estimated: np.ndarray) -> np.ndarray:
    """(N, 3) vector part of q_ref * conj(q) with the sign that makes w >= 0 (eq. 3, 6)."""
    e = quaternion_multiply_xyzw(q_reference, q_estimated * np.array([-1.0, -1.0, -1.0, 1.0]))
    e = e / np.linalg.norm(e, axis=1, keepdims=True)
    return np.where(e[:, 3:4] < 0, -e[:, :3], e[:, :3])


def fit_polynomial_lstsq(degree: int, reported_positions: np.ndarray, reported_quaternions_xyzw: np.ndarray,
                         reference_positions: np.ndarray, reference_quaternions_xyzw: np.ndarray):
    """The paper's eq. 7 by plain numpy least squares on positions normalised to the stations'
    bounding box: returns (position_coefficients (R, 3), orientation_coefficients (R, 3),
    input_offset, input_scale). The fit engine's lone polynomial solves the same problem."""
    p = np.asarray(reported_positions, dtype=float)
    lo, hi = p.min(axis=0), p.max(axis=0)
    offset = 0.5 * (lo + hi)
    scale = np.maximum(0.5 * (hi - lo), 1e-6)
    a = monomials(degree, (p - offset) / scale)
    if a.shape[0] < a.shape[1]:
        raise ValueError(f"{a.shape[0]} stations cannot fit a degree-{degree} polynomial ({a.shape[1]} terms)")
    pc = np.linalg.lstsq(a, np.asarray(reference_positions) - p, rcond=None)[0]
    oc = np.linalg.lstsq(a, orientation_error_vectors(np.asarray(reference_quaternions_xyzw),
                                                      np.asarray(reported_quaternions_xyzw)), rcond=None)[0]
    return pc, oc, offset, scale
