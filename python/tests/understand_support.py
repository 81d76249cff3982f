"""Shared helpers of the Understand tests: simulated captures (trackcal-simulate, fixed seeds) and a
poses.csv writer for hand-built captures."""

from __future__ import annotations

import pathlib
import shutil
import subprocess

import numpy as np

HEADER = ["station", "set", "sensor", "time", "rep_x", "rep_y", "rep_z", "rep_qw", "rep_qx", "rep_qy",
          "rep_qz", "ref_x", "ref_y", "ref_z", "ref_qw", "ref_qx", "ref_qy", "ref_qz"]


def simulate(out: pathlib.Path, seed: int = 7, hidden: str = "") -> pathlib.Path:
    exe = shutil.which("trackcal-simulate")
    assert exe, "trackcal-simulate must be on PATH (scripts/build.sh installs it into the venv)"
    cmd = [exe, "--scene", "paper", "--seed", str(seed), "-o", str(out)]
    if hidden:
        cmd[3:3] = ["--hidden", hidden]
    subprocess.run(cmd, check=True, capture_output=True)
    return out


def write_poses(path: pathlib.Path, capture, extra: dict = None) -> pathlib.Path:
    """Writes a PoseCapture-like object (arrays, quaternions x, y, z, w) as poses.csv with extra
    columns {name: (N,) values}."""
    extra = extra or {}
    names = HEADER + list(extra)
    lines = [",".join(names)]
    for i in range(len(capture.station)):
        rp, rq = capture.reported_positions[i], capture.reported_quaternions_xyzw[i]
        fp, fq = capture.reference_positions[i], capture.reference_quaternions_xyzw[i]
        row = [str(int(capture.station[i])), str(capture.set[i]), str(int(capture.sensor[i])),
               repr(float(capture.time[i]))]
        row += [repr(float(v)) for v in (*rp, rq[3], rq[0], rq[1], rq[2], *fp, fq[3], fq[0], fq[1], fq[2])]
        row += [repr(float(v[i])) for v in extra.values()]
        lines.append(",".join(row))
    path.write_text("\n".join(lines) + "\n")
    return path


def quat_about_z_xyzw(angle_rad):
    a = np.asarray(angle_rad, dtype=float)
    return np.stack([np.zeros_like(a), np.zeros_like(a), np.sin(a / 2), np.cos(a / 2)], axis=-1)
