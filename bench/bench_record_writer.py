#!/usr/bin/env python3
"""The live recorder's writer (trackcal.record): how fast a flush's reports become tracker_stream.csv
rows, in the same run for the old and the new formatter.

    .venv/bin/python bench/bench_record_writer.py [--rows 480] [--chunks 200] [--repeats 5] [--live 11]

A chunk is one flush (1 s) of one device: 4 sensors at 120 Hz are 480 rows. Prints rows/s, best of
the repeats, of
  old:  the capture writer (save_tracker_stream) into a file under a scratch folder, read back, the
        header cut off (trackcal.record before format_tracker_stream);
  new:  format_tracker_stream(header=False), in memory;
  writer: the whole _StreamFile.append (formatting, checks and the write into its .partial),
and the ratio new / old. Then the cost of the .partial's fsync every 5 s (_FSYNC_S):
  writer: the appends with sync() after every 5th flush (5 s of recording) against none, rows/s
        and ratio, best of the repeats;
  live: record_streams of a simulated device reporting --rows per second on the clock for --live
        seconds, with the fsync and without (_FSYNC_S out of reach), one run each: rows recorded
        per second recorded and the process's CPU seconds, as ratios.
Pin to one core for a steadier figure: `taskset -c 0 ...`.
"""

from __future__ import annotations

import argparse
import pathlib
import tempfile
import time

import numpy as np

from trackcal import record
from trackcal.captures import TrackerStream, format_tracker_stream, save_tracker_stream


def chunks(rows: int, count: int):
    """`count` flushes of `rows` reports as a TrackerRecorder's take() gives them (seed fixed)."""
    rng = np.random.default_rng(20261202)
    out = []
    for c in range(count):
        q = rng.normal(size=(rows, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        out.append({"time": 1796098746.0 + c + np.arange(rows) / rows, "sensor": (np.arange(rows) % 4).astype(np.int32),
                    "positions": rng.normal(scale=0.3, size=(rows, 3)), "quaternions_xyzw": q})
    return out


def stream_of(d) -> TrackerStream:
    return TrackerStream(d["time"], d["sensor"] + 1, d["positions"], d["quaternions_xyzw"])


def best_rate(fn, data, repeats: int) -> float:
    rows = sum(len(d["time"]) for d in data)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn(data)
        best = min(best, time.perf_counter() - start)
    return rows / best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=480, help="rows per flush (default: 4 sensors at 120 Hz)")
    parser.add_argument("--chunks", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--live", type=float, default=11.0, help="seconds of each live recording (0: none)")
    args = parser.parse_args()
    data = chunks(args.rows, args.chunks)

    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        scratch = tmp / "scratch.csv"

        def old(data):
            for d in data:
                save_tracker_stream(scratch, stream_of(d))
                text = scratch.read_bytes()
                scratch.unlink()
                text[text.index(b"\n") + 1:]

        def new(data):
            for d in data:
                format_tracker_stream(stream_of(d), name="x.partial", header=False)

        # Same bytes first: the benchmark compares equal work.
        save_tracker_stream(scratch, stream_of(data[0]))
        expected = scratch.read_bytes()
        scratch.unlink()
        assert format_tracker_stream(stream_of(data[0])) == expected

        def writer(data, sync_every=0):
            target = tmp / "w_tracker_stream.csv"
            f = record._StreamFile(target)
            for i, d in enumerate(data, 1):
                f.append(d)
                if sync_every and i % sync_every == 0:
                    f.sync()
            f.discard()
            f.partial.unlink()

        def synced(data):
            writer(data, sync_every=5)

        rates = {name: best_rate(fn, data, args.repeats) for name, fn in (("old", old), ("new", new),
                                                                           ("writer", writer),
                                                                           ("synced", synced))}
        for name, rate in rates.items():
            print(f"{name:>7}: {rate / 1e3:8.1f} k rows/s")
        print(f"new / old: {rates['new'] / rates['old']:.2f}x")
        print(f"writer with fsync every 5 flushes / without: {rates['synced'] / rates['writer']:.3f}")
        if args.live > 0:
            live = {}
            for name, period in (("without", 1e9), ("fsync 5 s", record._FSYNC_S)):
                live[name] = live_recording(tmp / name.replace(" ", "_"), args.rows, args.live, period)
                rows, recorded, cpu = live[name]
                print(f"live {name:>9}: {rows / recorded:8.1f} rows/s recorded, {cpu:.3f} s CPU")
            (r1, t1, c1), (r0, t0, c0) = live["fsync 5 s"], live["without"]
            print(f"live with fsync / without: rows/s {(r1 / t1) / (r0 / t0):.3f}, CPU {c1 / c0:.3f}")
    return 0


class ClockedRecorder:
    """A TrackerRecorder whose device reports `rate` poses per second, on the clock."""
    rate = 480

    def __init__(self, name):
        self.begun = time.monotonic()
        self.taken = 0
        self.rng = np.random.default_rng(1)

    def start(self):
        pass

    def stop(self):
        pass

    def __len__(self):
        return int((time.monotonic() - self.begun) * self.rate) + 1 - self.taken

    def take(self):
        n = len(self)
        self.taken += n
        q = self.rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        return {"time": 1796098746.0 + (self.taken - n + np.arange(n)) / self.rate,
                "sensor": (np.arange(n) % 4).astype(np.int32), "positions": self.rng.normal(scale=0.3, size=(n, 3)),
                "quaternions_xyzw": q}


def live_recording(folder: pathlib.Path, rate: int, seconds: float, fsync_period: float):
    """Rows recorded, seconds recorded and CPU seconds of one record_streams of a ClockedRecorder."""
    import types
    saved = record._core, record._FSYNC_S
    ClockedRecorder.rate = rate
    record._core = types.SimpleNamespace(TrackerRecorder=ClockedRecorder)
    record._FSYNC_S = fsync_period
    try:
        cpu = time.process_time()
        out = record.record_streams({"dev": "Tracker0@tcp://h:1"}, folder, seconds, waiting=None)
        cpu = time.process_time() - cpu
    finally:
        record._core, record._FSYNC_S = saved
    rows = out["dev"].read_bytes().count(b"\n") - 1
    return rows, seconds, cpu


if __name__ == "__main__":
    raise SystemExit(main())
