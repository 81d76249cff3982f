"""Shared helpers of the Understand tests: simulated captures (trackcal-simulate, fixed seeds) and a
poses.csv writer for hand-built captures."""

from __future__ import annotations

import pathlib
import shutil
import socket
import subprocess

import numpy as np

HEADER = ["station", "set", "sensor", "time", "rep_x", "rep_y", "rep_z", "rep_qw", "rep_qx", "rep_qy",
          "rep_qz", "ref_x", "ref_y", "ref_z", "ref_qw", "ref_qx", "ref_qy", "ref_qz"]


def free_port() -> int:
    """A TCP port free on the loopback interface now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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
    columns {name: (N,) values}, numbers or text."""
    extra = extra or {}
    names = HEADER + list(extra)
    lines = [",".join(names)]
    for i in range(len(capture.station)):
        rp, rq = capture.reported_positions[i], capture.reported_quaternions_xyzw[i]
        fp, fq = capture.reference_positions[i], capture.reference_quaternions_xyzw[i]
        row = [str(int(capture.station[i])), str(capture.set[i]), str(int(capture.sensor[i])),
               repr(float(capture.time[i]))]
        row += [repr(float(v)) for v in (*rp, rq[3], rq[0], rq[1], rq[2], *fp, fq[3], fq[0], fq[1], fq[2])]
        # Text values (an operator's name) are written as they are: a column of labels.
        row += [v[i] if isinstance(v[i], str) else repr(float(v[i])) for v in extra.values()]
        lines.append(",".join(row))
    path.write_text("\n".join(lines) + "\n")
    return path


def quat_about_z_xyzw(angle_rad):
    a = np.asarray(angle_rad, dtype=float)
    return np.stack([np.zeros_like(a), np.zeros_like(a), np.sin(a / 2), np.cos(a / 2)], axis=-1)


def receiver_gain_at(delta_t, per_degree=0.004, anisotropy=(1.5, 0.5, 1.0)):
    """Receiver coil gains G(T) = I + per_degree * (T - T0) * diag(anisotropy): every coil's gain
    drifts with temperature, at its own rate."""
    return np.diag([1.0 + per_degree * delta_t * a for a in anisotropy])



def stream_only(capture: pathlib.Path, out: pathlib.Path) -> pathlib.Path:
    """A new folder ``out`` with only the capture's two streams (tracker and reference): a folder
    trackcal pairs as a stream capture."""
    from trackcal.captures import STREAM_FILES
    out.mkdir()
    for name in STREAM_FILES:
        shutil.copy(capture / name, out / name)
    return out

def simulate_temperature_gains(out: pathlib.Path, *, levels=np.arange(18.0, 31.0, 2.0), seed: int = 5,
                               per_degree: float = 0.004, base: str = "ideal") -> pathlib.Path:
    """A capture whose receiver gains follow the room temperature, an effect outside the fit
    engine's catalog (its receiver_gain term is one constant G).

    How: the C++ simulator (trackcal-simulate, the physics of core/field.h and the Fastrak's
    free-space solver) renders the same capture (same seed: same stations, orientations and noise)
    once per temperature level, with tracker.receiver_gain_matrix = G(level) from
    ``receiver_gain_at`` (levels symmetric around their mean T0, so the average gain is the
    identity). Each station then takes its reported and reference poses from the rendering at a
    randomly drawn level; its ``temperature`` column is that level plus a uniform +-0.5 degC reading
    spread. A ``humidity`` column unrelated to anything is added as a control. Registration
    stations come from the T0-nearest level. Writes ``out/poses.csv`` (written by ``write_poses``)
    and returns the folder."""
    import dataclasses

    from trackcal import captures

    exe = shutil.which("trackcal-simulate")
    assert exe, "trackcal-simulate must be on PATH (scripts/build.sh installs it into the venv)"
    out.mkdir(parents=True)
    levels = np.asarray(levels, dtype=float)
    t0 = float(levels.mean())
    rendered = []
    for k, level in enumerate(levels):
        gain = receiver_gain_at(level - t0, per_degree)
        rows = ", ".join("[" + ", ".join(repr(float(x)) for x in row) + "]" for row in gain)
        scene = out / f"scene_{k}.yaml"
        scene.write_text(f"base: {base}\nseed: {seed}\ntracker:\n  receiver_gain_matrix: [{rows}]\n"
                         "capture:\n  stream:\n    duration_s: 0\n")
        subprocess.run([exe, "--scene", str(scene), "-o", str(out / f"level_{k}")], check=True,
                       capture_output=True)
        rendered.append(captures.load_poses(out / f"level_{k}"))
    first = rendered[0]
    for r in rendered:
        assert np.array_equal(r.station, first.station)
    n = len(first)
    rng = np.random.default_rng(seed)
    level = rng.integers(0, len(levels), n)
    level[first.set == "reg"] = int(np.argmin(np.abs(levels - t0)))
    rows = np.arange(n)

    def pick(name):
        return np.stack([getattr(r, name) for r in rendered])[level, rows]

    cap = dataclasses.replace(first, reported_positions=pick("reported_positions"),
                              reported_quaternions_xyzw=pick("reported_quaternions_xyzw"),
                              reference_positions=pick("reference_positions"),
                              reference_quaternions_xyzw=pick("reference_quaternions_xyzw"))
    capture_dir = out / "capture"
    capture_dir.mkdir()
    write_poses(capture_dir / "poses.csv", cap,
                extra={"temperature": levels[level] + rng.uniform(-0.5, 0.5, n),
                       "humidity": rng.uniform(30.0, 60.0, n)})
    return capture_dir


def two_receivers(capture_dir):
    """The capture's stations as receiver 1 and again as receiver 2, whose body (the reference)
    sits 3.7 cm further: a lab that captured its head and hand receivers into one poses.csv.
    Returns (both receivers' PoseCapture, receiver 2's alone)."""
    import dataclasses
    from trackcal import captures
    one = captures.load_poses(capture_dir)
    fields = {}
    for f in dataclasses.fields(one):
        v = getattr(one, f.name)
        if isinstance(v, np.ndarray):
            w = v.copy()
            if f.name == "sensor":
                w[:] = 2
            elif f.name == "reference_positions":
                w = w + np.array([0.03, -0.02, 0.01])  # the other body's offset
            v = np.concatenate([v, w])
        fields[f.name] = v
    mixed = captures.PoseCapture(**fields)
    return mixed, mixed.subset(mixed.sensor == 2)
