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
import sys
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence, Set, Tuple

import numpy as np

from trackcal import _core
from trackcal._signals import signals_deferred
from trackcal.captures import TrackerStream, format_tracker_stream


class NoFirstReport(RuntimeError):
    """A device sent no report within the connect timeout: nothing was recorded."""


class UnknownHost(NoFirstReport):
    """A device's host name does not resolve: failed at once, not after the connect timeout (a
    longer one would not help)."""


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


def _to_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def record_streams(devices: Dict[str, str], out_dir, duration_s: float, *, connect_timeout_s: float = 10.0,
                   progress: Optional[Callable[[float, float], None]] = None,
                   waiting: Optional[Callable[[str], None]] = _to_stderr) -> Recording:
    """Records every named device (label -> 'Tracker0@tcp://host:port') for ``duration_s`` seconds
    after all have connected, and writes ``<label>_tracker_stream.csv`` into out_dir. The reports
    are appended to ``<label>_tracker_stream.csv.partial`` every second as they arrive (a killed
    process leaves them there; they are fsynced every 5 s, so a power cut keeps them too) and the
    file takes its name at the end. The .partial files are made when every device has sent its
    first report (a process killed while it waits leaves none). Recordings are never
    overwritten: out_dir must hold neither name already (ValueError), and a file that appears under
    the name during the recording is kept, this recording staying in its .partial, named in the
    error. Returns label -> path.
    Raises NoFirstReport (a RuntimeError) if a device sends no report within connect_timeout_s
    (nothing is recorded then; the message says of each whether its host name is unknown, no
    server answered, or the server did not serve its name), and its UnknownHost as soon as a
    device's host name fails to resolve, without waiting out the timeout. A wait longer than 1 s is announced by
    one line, "waiting up to N s for the first report from: LABEL (NAME), ...", given to
    ``waiting`` (default: printed to stderr; None: not said). RuntimeError if one sends no report
    during the recording, loses its connection during it (a server that stopped or went away: its
    recording is saved but has a gap or ends early), or sends nothing for longer than max(1 s, 10
    of its mean intervals between reports) while connected (a frozen server or a lost network,
    which the client notices only after its 10 s liveness timeout), or sends reports the capture
    writer refuses (a non-finite value, a quaternion of norm not 1: left out, the rest recorded),
    or a report at a time its sensor already had (a server clock that did not tick or stepped back
    onto it, a report sent twice: left out, so that the recording loads), after saving every
    recording (the message names them).

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
            return _record(devices, out_dir, duration_s, connect_timeout_s, progress, waiting, terminated)
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
    """Why a device sent no report, as its client sees it: a host name that does not resolve, no
    connection (no server there), no answer to the pings for its name (a name the server does not
    serve), or served and quiet."""
    connected = getattr(recorder, "connected", None)
    if connected is None:  # a recorder that does not say
        return ""
    if not connected and getattr(recorder, "host_unknown", False):  # not a server that is down
        return (f": unknown host {getattr(recorder, 'host', '')!r} (the name does not resolve to an address: "
                "a typo, or no DNS?)")
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


# Rows leave memory for the recording's .partial file at least this often [s]: a process killed
# outright (SIGKILL, the OOM killer, a crash) leaves every row up to the last flush on disk, and a
# recorder holds at most about this long of reports. Kept in memory to the end, an hour of 4 sensors
# at 120 Hz, raw and corrected, grew the process by ~330 MB and to ~1.2 GB while it was saved.
_FLUSH_S = 1.0


# The .partial files are fsynced this often [s]: appended every second, the rows stayed in the page
# cache until the save, and a power cut or a kernel crash could take the whole recording with it.
# Measured by bench/bench_record_writer.py: see docs/benchmarks.md.
_FSYNC_S = 5.0

# A wait for the first reports longer than this is announced [s] (it looked hung).
_WAITING_NOTICE_S = 1.0


def _record(devices: Dict[str, str], out_dir: pathlib.Path, duration_s: float, connect_timeout_s: float,
            progress: Optional[Callable[[float, float], None]], waiting: Optional[Callable[[str], None]],
            terminated: Set[int]) -> Recording:
    """record_streams into the existing folder out_dir; a SIGTERM or SIGHUP that arrives while it
    saves is added to ``terminated``."""
    targets = {label: out_dir / f"{label}_tracker_stream.csv" for label in devices}
    for p in targets.values():
        if p.exists():
            raise ValueError(f"{p}: exists; recordings are never overwritten")
        if _StreamFile.partial_of(p).exists():  # refused before any device is contacted
            raise ValueError(_StreamFile.partial_exists(p))
    files: Dict[str, _StreamFile] = {}
    try:
        return _record_into(targets, files, devices, duration_s, connect_timeout_s, progress, waiting,
                            terminated)
    finally:  # one still open after an error: removed when it holds no row, else kept
        for f in files.values():
            f.discard()


def _record_into(targets: Dict[str, pathlib.Path], files: Dict[str, "_StreamFile"], devices: Dict[str, str],
                 duration_s: float, connect_timeout_s: float, progress: Optional[Callable[[float, float], None]],
                 waiting: Optional[Callable[[str], None]], terminated: Set[int]) -> Recording:
    """_record once the targets are checked; makes each recording's .partial file into ``files``
    when every device has sent its first report."""
    recorders = {label: _core.TrackerRecorder(name) for label, name in devices.items()}
    out = Recording()
    started = False
    lost: Dict[str, float] = {}
    silent: Dict[str, Tuple[float, float]] = {}
    recorded_s = 0.0  # how long the recording ran: the duration, or until an interruption
    counts: Dict[str, int] = {}  # label -> reports at the last look
    heard: Dict[str, float] = {}  # label -> seconds into the recording of the last growth

    def received(label: str) -> int:  # reports since the start: written, and waiting in the recorder
        return files[label].rows + len(recorders[label])
    for r in recorders.values():
        r.start()
    try:
        begun = time.monotonic()
        deadline = begun + connect_timeout_s
        announced = waiting is None
        while not all(len(r) > 0 for r in recorders.values()):
            now = time.monotonic()
            # A name that does not resolve reaches no server however long we wait: waiting out the
            # connect timeout (as long as the user asked for) only delayed the same error.
            unknown = [f"{label} ({devices[label]}{_why_silent(r)})" for label, r in recorders.items()
                       if len(r) == 0 and getattr(r, "host_unknown", False)]
            if unknown:
                raise UnknownHost(f"no report from: {', '.join(unknown)}")
            if now > deadline:
                missing = [f"{label} ({devices[label]}{_why_silent(r)})" for label, r in recorders.items()
                           if len(r) == 0]
                raise NoFirstReport(f"no report within {connect_timeout_s} s from: {', '.join(missing)}")
            if not announced and now - begun >= _WAITING_NOTICE_S:
                announced = True
                silent_devices = [f"{label} ({devices[label]})" for label, r in recorders.items() if len(r) == 0]
                waiting(f"waiting up to {connect_timeout_s:g} s for the first report from: "
                        f"{', '.join(silent_devices)}")
            time.sleep(0.02)
        # Made now, not before the wait: a process killed while it waited (a server not up yet)
        # left a .partial holding only the header, which refused every later recording of the label.
        for label, p in targets.items():
            files[label] = _StreamFile(p)
        for r in recorders.values():
            r.take()  # start all streams at the same moment
        started = True
        t0 = time.monotonic()
        flushed = synced = 0.0
        # A server that freezes or whose network goes (a pulled cable) keeps its connection open
        # until the client's liveness timeout (10 s): the recording just stopped growing and was
        # saved as if complete. Each device's longest silence is watched too.
        counts.update({label: received(label) for label in recorders})
        heard.update(dict.fromkeys(recorders, 0.0))
        while (elapsed := time.monotonic() - t0) < duration_s:
            recorded_s = elapsed
            # A server that goes away mid-recording: the client reconnects on its own, so the
            # recording just stopped growing and was saved as if complete.
            for label, r in recorders.items():
                if label not in lost and not getattr(r, "connected", True):
                    lost[label] = elapsed
                _watch_silence(label, received(label), elapsed, counts, heard, silent)
            if elapsed - flushed >= _FLUSH_S:
                _flush(files, recorders, terminated)
                flushed = elapsed
            if elapsed - synced >= _FSYNC_S:
                for f in files.values():
                    f.sync()
                synced = elapsed
            if progress:
                progress(elapsed, duration_s)
            time.sleep(min(0.1, duration_s - elapsed) if duration_s > elapsed else 0)
        recorded_s = duration_s
        for label in recorders:
            _watch_silence(label, received(label), duration_s, counts, heard, silent)
        if progress:
            progress(duration_s, duration_s)  # the bar ends at 100 % (and its line) before the summary
    except KeyboardInterrupt:  # Ctrl-C: stop recording and keep what was recorded
        out.interrupted = True
        if heard:  # the silence up to the interruption counts, as up to the end of a full one
            recorded_s = min(max(recorded_s, time.monotonic() - t0), duration_s)
            for label in recorders:
                _watch_silence(label, received(label), recorded_s, counts, heard, silent)
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
            return _finish(out, recorders, files, devices, started, lost, silent, duration_s, recorded_s,
                           ctrl_c)
        finally:
            terminated.update(ctrl_c - {signal.SIGINT})


def _flush(files: Dict[str, "_StreamFile"], recorders, terminated: Set[int]) -> None:
    """Appends every recorder's reports so far to its .partial file. Ctrl-C, SIGTERM and SIGHUP wait
    until they are written (taken and not written, they were lost), then end the recording."""
    with signals_deferred((signal.SIGINT, *_TERMINATIONS)) as arrived:
        for label, r in recorders.items():
            files[label].append(r.take())
    if arrived:
        terminated.update(arrived - {signal.SIGINT})
        raise KeyboardInterrupt


class _StreamFile:
    """One device's recording, appended as it arrives to ``<target>.partial`` and moved to the
    target when it ends. The .partial is made new: one that exists (a recording killed before it
    ended, one kept beside a file that appeared under its name, or one still running into the same
    folder) is never touched, and refuses the start. The rows are formatted in memory by the capture
    writer's C++ (format_tracker_stream) a flush at a time, so the file is the one it writes of all
    at once. (Written to a file under /tmp and read back, they took 2.5-12 times as long, and a
    SIGKILL left the folder there.)"""

    @staticmethod
    def partial_of(target: pathlib.Path) -> pathlib.Path:
        return target.with_name(target.name + ".partial")

    @staticmethod
    def partial_exists(target: pathlib.Path) -> str:
        """The error for a .partial that is there before the recording makes it."""
        return (f"{_StreamFile.partial_of(target)}: exists (a recording killed before it ended, kept beside "
                f"{target.name}, or still running into this folder); recordings are never overwritten: "
                "move it away or record into another folder")

    def __init__(self, target: pathlib.Path):
        self.target = target
        self.partial = self.partial_of(target)
        self._folder_synced = False
        self.rows = 0
        self.error: Optional[str] = None  # a write that failed (a full disk): the rows before it are kept
        self.seen = 0  # reports given to append
        self.refused = 0  # reports the capture writer refused, left out
        self.first_refusal = ""
        self.repeated = 0  # reports at a time their sensor already had, left out
        self.first_repeat = ""
        # sensor -> the times recorded (8 bytes a report), and the latest of them: a time a sensor
        # already had is left out, so that the recording loads (one sample per sensor and time).
        # The times are one sorted array and the in-order takes appended since (each after all
        # before it), joined only when a take is not simply after its sensor's latest time: looked
        # up by bisection there, instead of every time recorded concatenated and sorted again for
        # each such take (after a clock stepped back, every take until it is past its latest).
        self._sorted_times: Dict[int, np.ndarray] = {}
        self._times_after: Dict[int, List[np.ndarray]] = {}
        self._latest: Dict[int, float] = {}
        self._fd: Optional[int] = None
        header = self._csv(TrackerStream(np.zeros(0), np.zeros(0, dtype=np.int32), np.zeros((0, 3)),
                                         np.zeros((0, 4))), header=True)
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND | getattr(os, "O_CLOEXEC", 0)
        try:
            self._fd = os.open(self.partial, flags, 0o666)
        except FileExistsError:
            raise ValueError(self.partial_exists(target)) from None
        except OSError as e:
            raise ValueError(f"{self.partial}: cannot create the recording ({e.strerror})") from None
        try:
            self._write(header)
        except OSError as e:
            self.discard()
            raise ValueError(f"{self.partial}: cannot write the recording ({e.strerror})") from None

    def _csv(self, stream: TrackerStream, header: bool = False) -> bytes:
        """The stream's rows as the capture writer writes them; its refusals name the .partial."""
        return format_tracker_stream(stream, name=str(self.partial), header=header)

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self._fd, view):]

    def append(self, d) -> None:
        """Appends the reports of one take() (VRPN numbers sensors from 0, capture files from 1). A
        report the capture writer refuses (a non-finite value, a quaternion that is not a rotation)
        is left out and counted. After a failed write the reports are dropped (reported at the end)."""
        n = len(d["time"])
        if n == 0 or self._fd is None or self.error:
            return
        stream = TrackerStream(d["time"], d["sensor"] + 1, d["positions"], d["quaternions_xyzw"])
        # numbers: each row's place in the take, so that a refusal after a repeat left out is
        # numbered as the reports came.
        stream, numbers = self._without_repeats(stream)
        try:
            try:
                rows = self._csv(stream)
            except ValueError as refusal:
                stream, rows = self._without_refused(stream, refusal, numbers)
            self._write(rows)
        except OSError as e:
            self.error = f"{self.partial}: write failed: {e.strerror}"
            return
        except (ValueError, RuntimeError) as e:
            self.error = str(e)
            return
        finally:
            self.seen += n
        self.rows += len(stream.time)

    @staticmethod
    def _writable(stream: TrackerStream) -> np.ndarray:
        """Which reports the capture writer takes, one by one (finite, a unit quaternion)."""
        q_norm = np.linalg.norm(stream.quaternions_xyzw, axis=1)
        return (np.isfinite(stream.time) & np.isfinite(stream.positions).all(axis=1)
                & np.isfinite(stream.quaternions_xyzw).all(axis=1) & (np.abs(q_norm - 1.0) <= 1e-3))

    def _without_repeats(self, stream: TrackerStream) -> Tuple[TrackerStream, np.ndarray]:
        """The stream without the reports at a time their sensor already had (in this take, or
        recorded before): a server clock that did not tick, or stepped back onto a time it gave, or
        a report sent twice. Kept, they made a recording that saved and then failed to load
        (docs/captures.md). They are counted, and the first is kept for the error. A time before the
        sensor's latest that it never had (a clock stepped back) is kept: nothing repeats. Also
        returns the kept rows' indices in ``stream``."""
        writable = self._writable(stream)  # the others are the writer's refusals, counted there
        keep = np.ones(len(stream.time), dtype=bool)
        for sensor in np.unique(stream.sensor[writable]):
            rows = np.flatnonzero(writable & (stream.sensor == sensor))
            t = stream.time[rows]
            key = int(sensor)
            latest = self._latest.get(key, -math.inf)
            if t[0] > latest and (len(t) < 2 or (np.diff(t) > 0).all()):  # simply in order
                self._times_after.setdefault(key, []).append(t)
                self._latest[key] = float(t[-1])
                continue
            earlier = self._sorted_times.get(key, np.zeros(0))
            if key in self._times_after:  # sorted too: each take after every time before it
                earlier = np.concatenate([earlier] + self._times_after.pop(key))
            new = np.zeros(len(t), dtype=bool)
            new[np.unique(t, return_index=True)[1]] = True  # the first of equal times in the take
            if len(earlier):
                at = np.minimum(np.searchsorted(earlier, t), len(earlier) - 1)
                new &= earlier[at] != t
            keep[rows[~new]] = False
            t = np.sort(t[new])
            self._sorted_times[key] = np.insert(earlier, np.searchsorted(earlier, t), t)
            if len(t):
                self._latest[key] = max(latest, float(t[-1]))
        if keep.all():
            return stream, np.arange(len(stream.time))
        if self.repeated == 0:
            first = int(np.flatnonzero(~keep)[0])
            self.first_repeat = (f"report {self.seen + first} of the recording: time {float(stream.time[first])!r} of "
                                 f"sensor {int(stream.sensor[first])} repeats an earlier report's (one sample per "
                                 "sensor and time: a server clock that did not tick or went back, or a report "
                                 "sent twice)")
        self.repeated += int((~keep).sum())
        return (TrackerStream(stream.time[keep], stream.sensor[keep], stream.positions[keep],
                              stream.quaternions_xyzw[keep]), np.flatnonzero(keep))

    def _without_refused(self, stream: TrackerStream, refusal: ValueError,
                         numbers: np.ndarray) -> Tuple[TrackerStream, bytes]:
        """The stream without the reports the capture writer refuses, and its rows; the first
        refusal is kept for the error (which numbers the reports of the recording from 0; ``numbers``:
        each row's place in the take, which differs from its row after a repeat left out)."""
        good = self._writable(stream)
        if good.all():  # refused for another reason: not a report's fault
            raise refusal
        if self.refused == 0:
            first = int(np.flatnonzero(~good)[0])
            try:
                self._csv(TrackerStream(stream.time[first:first + 1], stream.sensor[first:first + 1],
                                        stream.positions[first:first + 1],
                                        stream.quaternions_xyzw[first:first + 1]))
            except ValueError as e:  # "<partial>: record 0: column x: nan is not a finite number"
                why = str(e).split(": record 0: ", 1)[-1]
                self.first_refusal = f"report {self.seen + int(numbers[first])} of the recording: {why}"
        self.refused += int((~good).sum())
        kept = TrackerStream(stream.time[good], stream.sensor[good], stream.positions[good],
                             stream.quaternions_xyzw[good])
        return kept, self._csv(kept)

    def sync(self) -> None:
        """fsyncs the rows written so far (and, the first time, the folder's entry for the file), so
        a power cut keeps them. A failure is the recording's error, as a failed write is."""
        if self._fd is None or self.error:
            return
        try:
            os.fsync(self._fd)
        except OSError as e:
            self.error = f"{self.partial}: write failed: {e.strerror}"
            return
        if not self._folder_synced:
            self._folder_synced = True
            try:  # best effort: some systems (Windows) cannot open or fsync a folder
                folder = os.open(self.partial.parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
                try:
                    os.fsync(folder)
                finally:
                    os.close(folder)
            except OSError:
                pass

    def close(self) -> Optional[str]:
        """Moves the finished recording to the target; None, or why it stays in the .partial."""
        fd, self._fd = self._fd, None
        try:
            os.fsync(fd)
        except OSError as e:
            self.error = self.error or f"{self.partial}: write failed: {e.strerror}"
        finally:
            os.close(fd)
        if self.error:
            return self.error
        try:
            os.link(self.partial, self.target)  # fails when the target exists, however late it came
        except FileExistsError:
            return f"{self.target}: exists; recordings are never overwritten (it appeared during the recording)"
        except OSError as e:  # a file system without hard links: nothing that could replace the file
            return f"{self.target}: not written ({e.strerror})"
        os.unlink(self.partial)
        return None

    def discard(self) -> None:
        """Closes the .partial if still open, and removes it when it holds no row (nothing was
        recorded); rows stay in it (an error that ended the recording left it behind)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
            if self.rows == 0:
                self.partial.unlink(missing_ok=True)


def _finish(out: "Recording", recorders, files: Dict[str, _StreamFile], devices, started: bool, lost, silent,
            duration_s: float, recorded_s: float, ctrl_c: Set[int]) -> "Recording":
    """Saves every recording after the recording stopped; the problems are raised after saving."""
    if not started:
        return out
    empty: List[str] = []
    failed: List[str] = []
    out_counts: Dict[str, int] = {}
    for label, r in recorders.items():  # every recording is saved before an empty one is reported
        f = files[label]
        f.append(r.take())
        out_counts[label] = f.rows
        if f.rows == 0 and not f.error and not f.refused and not f.repeated:
            empty.append(label)
            f.discard()
            continue
        why = f.close()
        if why:  # the recording stays in its .partial, named in the message
            failed.append(f"{why}: this recording ({f.rows} rows) is kept in {f.partial}")
            out[label] = f.partial
            continue
        out[label] = f.target
        if f.refused:
            failed.append(f"{f.target}: {f.refused} report{'s' if f.refused > 1 else ''} left out (the first, "
                          f"{f.first_refusal})")
        if f.repeated:
            failed.append(f"{f.target}: {f.repeated} report{'s' if f.repeated > 1 else ''} left out (the first, "
                          f"{f.first_repeat})")
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
