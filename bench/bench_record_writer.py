#!/usr/bin/env python3
"""The live recorder's writer (trackcal.record): how fast a flush's reports become tracker_stream.csv
rows, in the same run for the old and the new formatter.

    .venv/bin/python bench/bench_record_writer.py [--rows 480] [--chunks 200] [--repeats 5]

A chunk is one flush (1 s) of one device: 4 sensors at 120 Hz are 480 rows. Prints rows/s, best of
the repeats, of
  old:  the capture writer (save_tracker_stream) into a file under a scratch folder, read back, the
        header cut off (trackcal.record before format_tracker_stream);
  new:  format_tracker_stream(header=False), in memory;
  writer: the whole _StreamFile.append (formatting, checks and the write into its .partial),
and the ratio new / old. Pin to one core for a steadier figure: `taskset -c 0 ...`.
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

        def writer(data):
            target = tmp / "w_tracker_stream.csv"
            f = record._StreamFile(target)
            for d in data:
                f.append(d)
            f.discard()
            f.partial.unlink()

        rates = {name: best_rate(fn, data, args.repeats) for name, fn in (("old", old), ("new", new),
                                                                           ("writer", writer))}
    for name, rate in rates.items():
        print(f"{name:>7}: {rate / 1e3:8.1f} k rows/s")
    print(f"new / old: {rates['new'] / rates['old']:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
