"""Recording live streams from a running VRPN server (trackcal-server) for a later validation: the
raw and the corrected tracker of a ``trackcal_Calibration ... raw=<name>`` line, each written as a
tracker_stream.csv (docs/captures.md) with the server's header time."""

from __future__ import annotations

import contextlib
import math
import os
import pathlib
import re
import signal
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence, Set, Tuple

from trackcal import _core
from trackcal._signals import signals_deferred
from trackcal.captures import TrackerStream, save_tracker_stream


class Recording(dict):
    """label -> path of each saved recording. ``interrupted``: Ctrl-C ended it before the duration;
    ``empty``: the labels of devices that sent nothing before the interruption (no file);
    ``lost``: label -> seconds into the recording when the device's connection dropped (its
    recording has a gap or ends early); ``gaps``: label -> (start, length) [s] of a silence of a
    device that stayed connected (a frozen server, a lost network) longer than max(1 s, 10 of its
    mean intervals between reports over the time recorded, up to an interruption)."""

    interrupted: bool = False
    empty: Sequence[str] = ()
    lost: Dict[str, float] = {}
    gaps: Dict[str, Tuple[float, float]] = {}


def record_streams(devices: Dict[str, str], out_dir, duration_s: float, *, connect_timeout_s: float = 10.0,
                   progress: Optional[Callable[[float, float], None]] = None) -> Recording:
    """Records every named device (label -> 'Tracker0@tcp://host:port') for ``duration_s`` seconds
    after all have connected, and writes ``<label>_tracker_stream.csv`` into out_dir (which must
    not hold such files already: recordings are never overwritten; one that appears there during the
    recording is kept, and the recording saved beside it as ``<label>_tracker_stream.csv.partial``,
    named in the error). Returns label -> path.
    Raises RuntimeError if a device does not connect (nothing is recorded then), sends no report
    during the recording, loses its connection during it (a server that stopped or went away: its
    recording is saved but has a gap or ends early), or sends nothing for longer than max(1 s, 10
    of its mean intervals between reports) while connected (a frozen server or a lost network,
    which the client notices only after its 10 s liveness timeout), after saving every recording
    (the message names them).

    Ctrl-C (KeyboardInterrupt) ends the recording early and returns normally with ``interrupted``
    set: every device's reports until then are saved (none if it came before all had connected,
    when the recording had not started). SIGTERM and SIGHUP (``kill``, ``timeout``, a job scheduler,
    a closed terminal) end it the same way, and once it is saved the signal takes its usual effect
    (by default it ends the process); one that is ignored (``nohup``) stays ignored.

    The folders this call makes (out_dir and its missing parents) are removed again when it writes
    nothing into them (an error, or Ctrl-C before all had connected); a folder that existed before,
    or that holds any file, is never removed."""
    # As `trackcal record --duration` checks: a negative or NaN duration recorded nothing and then
    # blamed the devices ("no report during the recording"), an infinite timeout never gave up.
    for name, value in (("duration_s", duration_s), ("connect_timeout_s", connect_timeout_s)):
        try:
            seconds = float(value)
        except (TypeError, ValueError):
            seconds = math.nan
        if not (math.isfinite(seconds) and seconds > 0):
            raise ValueError(f"{name} {value!r}: must be a positive number of seconds")
    if not devices:  # else it waited out the duration and returned no recording, no error
        raise ValueError("devices: none given (label -> 'Tracker0@tcp://host:port')")
    for label in devices:
        # The label names the file: it must stay one plain file name inside out_dir.
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.+-]*", label) or ".." in label:
            raise ValueError(f"device label {label!r}: use letters, digits and _ . + - (it names "
                             f"{label or '<label>'}_tracker_stream.csv)")
    out_dir = pathlib.Path(out_dir)
    created = [p for p in (out_dir, *out_dir.parents) if not p.exists()]  # deepest first
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:  # a file in the way or no permission: the caller's input, as everywhere
        _remove_empty_folders(created)
        raise ValueError(f"{out_dir}: cannot make the recording folder ({e.strerror}: {e.filename})") from None
    terminated: Set[int] = set()
    try:
        with _terminations_interrupt(terminated):
            return _record(devices, out_dir, duration_s, connect_timeout_s, progress, terminated)
    finally:
        _remove_empty_folders(created)
        if terminated:  # saved: now the signal does what it would have done (its handler is back)
            signal.raise_signal(min(terminated))


# Signals that stop a recording from outside (kill, timeout, a scheduler, a closed terminal). By
# default they ended the process at once and every report, held in memory until the end, was lost.
_TERMINATIONS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))


@contextlib.contextmanager
def _terminations_interrupt(arrived: Set[int]):
    """Inside the block SIGTERM and SIGHUP are noted in ``arrived`` and raise KeyboardInterrupt, so
    they end a recording as Ctrl-C does; the previous handlers are back after it. A signal that is
    ignored (nohup) or whose handler Python does not know is left alone, and so is everything outside
    the main thread, where handlers cannot be set."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, _frame):
        arrived.add(signum)
        raise KeyboardInterrupt

    previous = {s: signal.getsignal(s) for s in _TERMINATIONS}
    previous = {s: h for s, h in previous.items() if h is not None and h != signal.SIG_IGN}
    for s in previous:
        signal.signal(s, interrupt)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _why_silent(recorder) -> str:
    """Why a device sent no report, as its client sees it: no connection (no server there), no
    answer to the pings for its name (a name the server does not serve), or served and quiet."""
    connected = getattr(recorder, "connected", None)
    if connected is None:  # a recorder that does not say
        return ""
    if not connected:
        return ": no connection; is a server running at that address?"
    if not getattr(recorder, "pong_received", True):
        return ": connected, but no answer for this name; a device the server does not serve?"
    return ": connected and served, but no pose report"


_MIN_GAP_S = 1.0  # a silence shorter than this is never a gap (a VRPN tracker reports at 10 Hz or more)


def _watch_silence(label: str, count: int, elapsed: float, counts: Dict[str, int], heard: Dict[str, float],
                   silent: Dict[str, Tuple[float, float]]) -> None:
    """Notes, at ``elapsed`` seconds into the recording, whether the device sent a report since the
    last look, and keeps its longest silence as label -> (start [s into the recording], length [s])."""
    if count != counts[label]:
        counts[label] = count
        heard[label] = elapsed
        return
    length = elapsed - heard[label]
    if length > silent.get(label, (0.0, 0.0))[1]:
        silent[label] = (heard[label], length)


def _remove_empty_folders(folders: Sequence[pathlib.Path]) -> None:
    """Removes each folder (deepest first) while it is empty: rmdir refuses one that holds anything,
    and then its parents hold it."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


def _record(devices: Dict[str, str], out_dir: pathlib.Path, duration_s: float, connect_timeout_s: float,
            progress: Optional[Callable[[float, float], None]], terminated: Set[int]) -> Recording:
    """record_streams into the existing folder out_dir; a SIGTERM or SIGHUP that arrives while it
    saves is added to ``terminated``."""
    targets = {label: out_dir / f"{label}_tracker_stream.csv" for label in devices}
    for p in targets.values():
        if p.exists():
            raise ValueError(f"{p}: exists; recordings are never overwritten")
        # Where a recording is kept when a file appeared under its name: a recording too (as
        # trackcal-server --record refuses both names).
        partial = p.with_name(p.name + ".partial")
        if os.path.lexists(partial):
            raise ValueError(f"{partial}: exists (a recording kept beside {p.name}); recordings are "
                             "never overwritten: move it away or record into another folder")
    recorders = {label: _core.TrackerRecorder(name) for label, name in devices.items()}
    out = Recording()
    started = False
    lost: Dict[str, float] = {}
    silent: Dict[str, Tuple[float, float]] = {}
    recorded_s = 0.0  # how long the recording ran: the duration, or until an interruption
    counts: Dict[str, int] = {}  # label -> reports at the last look
    heard: Dict[str, float] = {}  # label -> seconds into the recording of the last growth
    for r in recorders.values():
        r.start()
    try:
        deadline = time.monotonic() + connect_timeout_s
        while not all(len(r) > 0 for r in recorders.values()):
            if time.monotonic() > deadline:
                missing = [f"{label} ({devices[label]}{_why_silent(r)})" for label, r in recorders.items()
                           if len(r) == 0]
                raise RuntimeError(f"no report within {connect_timeout_s} s from: {', '.join(missing)}")
            time.sleep(0.02)
        for r in recorders.values():
            r.take()  # start all streams at the same moment
        started = True
        t0 = time.monotonic()
        # A server that freezes or whose network goes (a pulled cable) keeps its connection open
        # until the client's liveness timeout (10 s): the recording just stopped growing and was
        # saved as if complete. Each device's longest silence is watched too.
        counts.update({label: len(r) for label, r in recorders.items()})
        heard.update(dict.fromkeys(recorders, 0.0))
        while (elapsed := time.monotonic() - t0) < duration_s:
            recorded_s = elapsed
            # A server that goes away mid-recording: the client reconnects on its own, so the
            # recording just stopped growing and was saved as if complete.
            for label, r in recorders.items():
                if label not in lost and not getattr(r, "connected", True):
                    lost[label] = elapsed
                _watch_silence(label, len(r), elapsed, counts, heard, silent)
            if progress:
                progress(elapsed, duration_s)
            time.sleep(min(0.1, duration_s - elapsed) if duration_s > elapsed else 0)
        recorded_s = duration_s
        for label, r in recorders.items():
            _watch_silence(label, len(r), duration_s, counts, heard, silent)
        if progress:
            progress(duration_s, duration_s)  # the bar ends at 100 % (and its line) before the summary
    except KeyboardInterrupt:  # Ctrl-C: stop recording and keep what was recorded
        out.interrupted = True
        if heard:  # the silence up to the interruption counts, as up to the end of a full one
            recorded_s = min(max(recorded_s, time.monotonic() - t0), duration_s)
            for label, r in recorders.items():
                _watch_silence(label, len(r), recorded_s, counts, heard, silent)
    except BaseException:  # a device that never connected: nothing recorded
        for r in recorders.values():
            r.stop()
        raise
    # A second Ctrl-C while stopping and saving escaped and lost every recording: from here it is
    # remembered, and ends the recording as an interruption once every file is saved.
    with signals_deferred((signal.SIGINT, *_TERMINATIONS)) as ctrl_c:
        try:
            for r in recorders.values():
                r.stop()
            return _finish(out, recorders, targets, devices, started, lost, silent, duration_s, recorded_s,
                           ctrl_c)
        finally:
            terminated.update(ctrl_c - {signal.SIGINT})


def _keep_beside(target: pathlib.Path, stream: TrackerStream) -> Optional[pathlib.Path]:
    """The recording saved as ``<target>.partial`` when a file appeared under the target's name
    during the recording (a second recording into the same folder), as trackcal-server --record
    keeps its own; that file is never replaced. None when the target is not there (a full disk, no
    permission: the same folder would refuse this too) or the .partial cannot be written either."""
    if not target.exists():
        return None
    partial = target.with_name(target.name + ".partial")
    try:
        save_tracker_stream(partial, stream)
    except (ValueError, RuntimeError, OSError):
        return None
    return partial


def _finish(out: "Recording", recorders, targets, devices, started: bool, lost, silent, duration_s: float,
            recorded_s: float, ctrl_c: Set[int]) -> "Recording":
    """Saves every recording after the recording stopped; the problems are raised after saving."""
    if not started:
        return out
    empty: List[str] = []
    failed: List[str] = []
    out_counts: Dict[str, int] = {}
    for label, r in recorders.items():  # every recording is saved before an empty one is reported
        d = r.take()
        out_counts[label] = len(d["time"])
        if len(d["time"]) == 0:
            empty.append(label)
            continue
        # VRPN numbers sensors from 0; capture files (and trackcal-server --record) from 1.
        stream = TrackerStream(d["time"], d["sensor"] + 1, d["positions"], d["quaternions_xyzw"])
        try:
            save_tracker_stream(targets[label], stream)
        except (ValueError, RuntimeError, OSError) as e:  # still save the others
            kept = _keep_beside(targets[label], stream)
            failed.append(str(e) + (f" (it appeared during the recording: this recording is kept in {kept})"
                                    if kept else ""))
            if kept:
                out[label] = kept
            continue
        out[label] = targets[label]
    out.empty = empty
    out.lost = lost
    gone = [label for label in lost if label not in empty]
    # The longest silence of each device that sent something and kept its connection: one over
    # max(1 s, 10 of its mean intervals between reports) is a gap (a frozen server, a lost network).
    gaps = {}
    for label, (start, length) in silent.items():
        n = out_counts.get(label, 0)
        if label in empty or label in lost or n == 0:
            continue
        # Mean intervals over the time recorded: Ctrl-C 60 s into an hour made them 60 times the
        # true ones, and a device frozen for most of the 60 s had no gap.
        if length > max(_MIN_GAP_S, 10.0 * recorded_s / n):
            gaps[label] = (start, length)
    out.gaps = gaps
    out.interrupted = out.interrupted or bool(ctrl_c)
    problems = failed + ([f"no report during the recording from: "
                          + ", ".join(f"{label} ({devices[label]})" for label in empty)]
                         if empty and not out.interrupted else [])
    if gone and not out.interrupted:
        problems.append("lost the connection during the recording to: "
                        + ", ".join(f"{label} ({devices[label]}) after {lost[label]:.1f} s of {duration_s:g} s"
                                    for label in gone)
                        + " (a recording with a gap or that ends early)")
    if gaps and not out.interrupted:
        problems.append("no report for a while during the recording from: "
                        + ", ".join(f"{label} ({devices[label]}) for {length:.1f} s from {start:.1f} s of "
                                    f"{duration_s:g} s" for label, (start, length) in gaps.items())
                        + " (a frozen server or a lost network: a recording with a gap or that ends early)")
    if problems:
        saved = f" (saved: {', '.join(str(p) for p in out.values())})" if out else ""
        raise RuntimeError("; ".join(problems) + saved)
    return out
