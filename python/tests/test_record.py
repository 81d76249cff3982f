"""Recording live raw and corrected streams from a trackcal-server serving a NULL tracker through a
calibration (raw= name), then validating the recording against the calibration."""

import functools
import pathlib
import shutil
import subprocess
import time

import numpy as np
import pytest

import trackcal
from trackcal import captures
from trackcal.record import record_streams
from understand_support import free_port

REPO = pathlib.Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "tests" / "data" / "calibration" / "example.json"


@pytest.fixture
def server(tmp_path):
    exe = shutil.which("trackcal-server")
    assert exe, "trackcal-server must be on PATH (scripts/build.sh installs it)"
    shutil.copy(EXAMPLE, tmp_path / "cal.json")
    (tmp_path / "vrpn.cfg").write_text("vrpn_Tracker_NULL Tracker0 2 100.0\n"
                                       "trackcal_Calibration Tracker0 cal.json raw=Tracker0_raw\n")
    port = free_port()
    proc = subprocess.Popen([exe, "-f", str(tmp_path / "vrpn.cfg"), str(port), "--bind", "127.0.0.1"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    time.sleep(0.3)
    yield port
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()


def test_record_raw_and_corrected(server, tmp_path):
    port = server
    out = record_streams({"raw": f"Tracker0_raw@tcp://127.0.0.1:{port}",
                          "corrected": f"Tracker0@tcp://127.0.0.1:{port}"}, tmp_path / "rec", 0.6)
    raw = captures.load_tracker_stream(out["raw"])
    cor = captures.load_tracker_stream(out["corrected"])
    # 2 sensors at 100 Hz for 0.6 s: ~120 reports each; at least a third arrives on a loaded machine.
    assert len(raw) > 40 and len(cor) > 40
    assert set(raw.sensor) == {1, 2}
    # NULL trackers report the identity pose; the corrected device serves the calibration applied to it.
    cal = trackcal.Calibration.load(EXAMPLE)
    p, q, _ = cal.correct(raw.positions[:1], raw.quaternions_xyzw[:1])
    np.testing.assert_allclose(raw.positions, 0.0, atol=0)
    # Wire values are doubles: the corrected stream equals the C++ correction exactly (1e-12 m slack
    # for a different evaluation order is not needed, but guards against a float32 path).
    np.testing.assert_allclose(cor.positions, np.repeat(p, len(cor), axis=0), atol=1e-12)
    assert np.abs(cor.positions).max() > 1e-4  # the example calibration does move the origin
    with pytest.raises(ValueError, match="never overwritten"):
        record_streams({"raw": f"Tracker0_raw@tcp://127.0.0.1:{port}"}, tmp_path / "rec", 0.1)


def test_record_unserved_name_times_out(server, tmp_path):
    with pytest.raises(RuntimeError, match="no report within"):
        record_streams({"x": f"Nope@tcp://127.0.0.1:{server}"}, tmp_path / "rec", 0.1, connect_timeout_s=1.5)


def test_a_device_that_never_reports_is_told_apart_from_a_missing_server(server, tmp_path):
    """A mistyped device name and a server that is not running both said only 'no report within
    10.0 s from: x (Nope@tcp://127.0.0.1:PORT)'. The client knows which: a server that is there
    connects, and answers the pings of a name it serves (vrpn_server/client/tracker_client.h)."""
    with pytest.raises(RuntimeError, match=r"no report within 3 s from: x \(Nope@tcp://127\.0\.0\.1:[0-9]+: "
                                           r"connected, but no answer for this name; a device the server "
                                           r"does not serve\?\), y \(Tracker0@tcp://127\.0\.0\.1:[0-9]+: "
                                           r"no connection; is a server running at that address\?\)$"):
        # 3 s: the connection and the first ping's answer take milliseconds on this host.
        record_streams({"x": f"Nope@tcp://127.0.0.1:{server}", "y": f"Tracker0@tcp://127.0.0.1:{free_port()}"},
                       tmp_path / "rec", 0.1, connect_timeout_s=3)


def test_a_failed_recording_removes_only_the_empty_folders_it_made(tmp_path):
    """Nothing listens on the port: no device connects, nothing is written. The folders the call
    made are removed again; a folder that existed before, empty or not, stays."""
    unserved = {"raw": f"Tracker0@tcp://127.0.0.1:{free_port()}"}
    # Nothing answers however long it waits: 0.5 s only bounds the test's time.
    record = functools.partial(record_streams, unserved, duration_s=0.1, connect_timeout_s=0.5)
    with pytest.raises(RuntimeError, match="no report within"):
        record(tmp_path / "new" / "rec")
    assert not (tmp_path / "new").exists()
    (tmp_path / "mine").mkdir()
    with pytest.raises(RuntimeError, match="no report within"):
        record(tmp_path / "mine")
    assert (tmp_path / "mine").is_dir()
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "todo.txt").write_text("keep\n")
    with pytest.raises(RuntimeError, match="no report within"):
        record(tmp_path / "notes" / "rec")
    assert sorted(p.name for p in (tmp_path / "notes").iterdir()) == ["todo.txt"]


def test_trackcal_record_without_a_server_leaves_no_folder(tmp_path, capsys):
    from trackcal import cli
    out = tmp_path / "run1"
    # The command waits 10 s for a device; 0.5 s is as conclusive when nothing listens.
    argv = ["record", "--device", f"raw=Tracker0@tcp://127.0.0.1:{free_port()}", "--duration", "1",
            "--connect-timeout", "0.5", "-o", str(out)]
    assert cli.main(argv) == 2
    assert "no report within 0.5 s from: raw" in capsys.readouterr().err
    assert not out.exists()


def test_trackcal_record_waits_for_the_first_reports_as_long_as_connect_timeout_says(tmp_path, capsys):
    """`trackcal record` waited 10 s for every device's first report, silently, a time no option
    changed and the help did not give: a mistyped host or port failed after 10 s of nothing, and a
    server still resetting its Fastrak (the driver's ~7 s of sleeps, more with a slow serial line)
    could not be waited for. --connect-timeout S sets it, and the error says how to wait longer."""
    from trackcal import cli
    out = tmp_path / "run1"
    argv = ["record", "--device", f"raw=Tracker0@tcp://127.0.0.1:{free_port()}", "--duration", "1",
            "-o", str(out), "--connect-timeout"]
    started = time.monotonic()
    assert cli.main(argv + ["0.5"]) == 2
    err = capsys.readouterr().err
    assert "no report within 0.5 s from: raw (Tracker0@tcp://127.0.0.1:" in err
    assert "--connect-timeout S to wait longer" in err
    # 0.5 s, the 20 ms polls and the client's stop: 5 s of slack for a loaded machine.
    assert time.monotonic() - started < 5.0
    for bad in ("0", "-1", "nan", "inf"):
        assert cli.main(argv + [bad]) == 2
        assert f"--connect-timeout {float(bad)}: must be a positive number of seconds" in capsys.readouterr().err
    assert not out.exists()
    sub = cli.build_parser()._subparsers._group_actions[0].choices["record"]
    assert "default 10" in sub.format_help()


def test_device_labels_name_one_file_each_inside_the_folder(tmp_path, capsys):
    from trackcal import cli, record
    out = tmp_path / "run1"
    # The same label twice would write both devices to one file (the second replaced the first).
    argv = ["record", "--device", "raw=Tracker0_raw@tcp://127.0.0.1:1", "--device",
            "raw=Tracker0@tcp://127.0.0.1:1", "--duration", "1", "-o", str(out)]
    assert cli.main(argv) == 2
    assert "label 'raw' is given twice" in capsys.readouterr().err
    # A label is a file name: no folders, nothing empty; checked before any folder is made.
    for label in ("../escaped", "", "a/b", ".hidden"):
        with pytest.raises(ValueError, match="device label"):
            record.record_streams({label: "Tracker0@tcp://127.0.0.1:1"}, out, 1.0, connect_timeout_s=0.1)
    assert not out.exists() and not (tmp_path / "escaped_tracker_stream.csv").exists()


def test_a_duration_that_records_nothing_is_refused_before_anything_is_made(fake_recorders, tmp_path):
    """record_streams(duration_s=-1 or nan) connected, recorded nothing and then reported the
    devices as silent ("no report during the recording"); `trackcal record --duration` refuses
    such values, and so does the function now, before any folder is made or device is contacted."""
    out = tmp_path / "rec"
    for bad in (0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=r"duration_s .*: must be a positive number of seconds"):
            record_streams({"raw": "Tracker0_raw@tcp://h:1"}, out, bad)
    with pytest.raises(ValueError, match=r"connect_timeout_s nan: must be a positive number"):
        record_streams({"raw": "Tracker0_raw@tcp://h:1"}, out, 1.0, connect_timeout_s=float("nan"))
    assert not out.exists() and not fake_recorders


def test_record_progress_ends_at_the_duration(server, tmp_path):
    calls = []
    record_streams({"raw": f"Tracker0_raw@tcp://127.0.0.1:{server}"}, tmp_path / "rec", 0.3,
                   progress=lambda done, total: calls.append((done, total)))
    # A terminal bar is finished (100 %, newline) only by a last call with done == total.
    assert calls and calls[-1] == (0.3, 0.3)


def test_a_live_recording_is_validated_later_against_the_reference(emulated_server, tmp_path):
    """Record the raw and corrected trackers of a server running on the emulator, then validate the
    recording against the reference (here the known pose of the still receiver, written as a
    reference stream, as an optical system would record it on its own clock)."""
    from trackcal import validation
    port, (p_true, q_true), cal_path = emulated_server
    # The server resets the Fastrak first (the driver's ~7 s of sleeps), hence the long timeout.
    out = record_streams({"raw": f"Tracker0_raw@tcp://127.0.0.1:{port}",
                          "corrected": f"Tracker0@tcp://127.0.0.1:{port}"}, tmp_path / "rec", 1.0,
                         connect_timeout_s=40.0)
    raw = captures.load_tracker_stream(out["raw"])
    t = np.arange(raw.time.min() - 0.5, raw.time.max() + 0.5, 0.01)
    reference = tmp_path / "rec" / "reference_stream.csv"
    rows = ["time,x,y,z,qw,qx,qy,qz"] + [f"{float(ti)!r},{p_true[0]},{p_true[1]},{p_true[2]},{q_true[3]},{q_true[0]},"
                                         f"{q_true[1]},{q_true[2]}" for ti in t]
    reference.write_text("\n".join(rows) + "\n")
    cal = trackcal.Calibration.load(cal_path)
    served = validation.validate_recording(out["raw"], reference, corrected=out["corrected"], calibration=cal,
                                           time_offset=0.0)
    applied = validation.validate_recording(out["raw"], reference, calibration=cal, time_offset=0.0)
    assert served.capture.origin["kind"] == "recording" and len(served.capture) > 20
    table = {t.set_name: t for t in served.tables}["all"]
    # The paper room bends the report at this pose by centimetres (22.9 mm measured); the degree-3
    # polynomial removes most of it (5.9 mm left at this pose, an identity orientation the capture's
    # stations rarely take), so half is a bound with margin that a wrong pairing or matching fails.
    assert table.before_position_mm["mean"] > 10.0
    assert table.after_position_mm["mean"] < 0.5 * table.before_position_mm["mean"]
    # What the server sent is the calibration applied to what it read (same C++ code, doubles on
    # the wire): the two validations agree to rounding.
    # The two recordings start and stop together, but a record's raw and corrected reports arrive
    # apart, so the record at either end can be in one of them only (CI: the corrected recording
    # began one record later); every record in both is compared.
    common = np.isin(applied.capture.station, served.capture.station)
    assert common.sum() >= len(applied.capture) - 2
    assert served.capture.station.tolist() == applied.capture.station[common].tolist()
    np.testing.assert_allclose(served.after.position_mm, applied.after.position_mm[common], atol=1e-9)
    print(f"recorded {len(served.capture)} samples: {table.before_position_mm['mean']:.2f} mm -> "
          f"{table.after_position_mm['mean']:.2f} mm")


class FakeRecorder:
    """A TrackerRecorder without a server: 3 reports before the synchronised start (discarded),
    5 after it; none after it when its name starts with 'empty', none at all with 'silent'."""
    instances = []

    def __init__(self, name):
        self.name, self.takes, self.stopped = name, 0, False
        FakeRecorder.instances.append(self)

    def start(self):
        pass

    def stop(self):
        self.stopped = True

    def __len__(self):
        return 0 if self.name.startswith("silent") else 3

    def take(self):
        self.takes += 1
        n = 3 if self.takes == 1 else (0 if self.name.startswith(("empty", "silent")) else 5)
        # Times go on from take to take, as a server's do: one sensor's time twice is not recorded.
        first, self.sent = getattr(self, "sent", 0), getattr(self, "sent", 0) + n
        return {"time": 100.0 + 0.01 * np.arange(first, first + n), "sensor": np.zeros(n, dtype=np.int32),
                "positions": np.full((n, 3), 0.25), "quaternions_xyzw": np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))}


@pytest.fixture
def fake_recorders(monkeypatch):
    import types
    from trackcal import record
    FakeRecorder.instances = []
    monkeypatch.setattr(record, "_core", types.SimpleNamespace(TrackerRecorder=FakeRecorder))
    return FakeRecorder.instances


class Arriving(FakeRecorder):
    """A TrackerRecorder whose reports arrive as the recording looks at it (len): 25 at each look,
    none after the second look when its name starts with 'frozen'. take() hands out, in order,
    the reports not taken yet, and ``after_start`` counts those that arrived after the first take
    (the synchronised start)."""

    def __init__(self, name):
        super().__init__(name)
        self.looks, self.arrived, self.taken, self.first = 0, 0, 0, None

    def __len__(self):
        self.looks += 1
        if not (self.name.startswith("frozen") and self.looks > 2):
            self.arrived += 25
        return self.arrived - self.taken

    def take(self):
        self.takes += 1
        i = np.arange(self.taken, self.arrived)
        self.taken = self.arrived
        if self.first is None:
            self.first = self.taken
        # Varying poses and sensors, so that a row written twice, lost or reordered shows.
        angle = 0.01 * i
        return {"time": 1796098746.0 + 0.001 * i, "sensor": (i % 2).astype(np.int32),
                "positions": np.column_stack([0.1 + i / 7e3, -0.2 - i / 3e4, 0.3 + np.sin(i)]),
                "quaternions_xyzw": np.column_stack([np.zeros_like(angle), np.zeros_like(angle),
                                                     np.sin(angle / 2), np.cos(angle / 2)])}

    @property
    def after_start(self):
        return self.taken - self.first


def test_an_empty_device_is_reported_after_the_others_are_saved(fake_recorders, tmp_path):
    rec = tmp_path / "rec"
    with pytest.raises(RuntimeError, match=r"no report during the recording from: corrected "
                                           r"\(empty@tcp://h:1\) \(saved: .*raw_tracker_stream\.csv\)"):
        record_streams({"corrected": "empty@tcp://h:1", "raw": "Tracker0_raw@tcp://h:1"}, rec, 0.05)
    raw = captures.load_tracker_stream(rec / "raw_tracker_stream.csv")
    assert len(raw) == 5 and set(raw.sensor) == {1}
    assert not (rec / "corrected_tracker_stream.csv").exists()
    assert all(r.stopped for r in fake_recorders)


def test_ctrl_c_ends_the_recording_and_keeps_what_was_recorded(fake_recorders, tmp_path):
    def ctrl_c(done, total):
        raise KeyboardInterrupt
    try:
        out = record_streams({"raw": "Tracker0_raw@tcp://h:1", "corrected": "empty@tcp://h:1"},
                             tmp_path / "rec", 3600.0, progress=ctrl_c)
    except KeyboardInterrupt:
        pytest.fail("Ctrl-C escaped record_streams: the recording is lost")
    assert out.interrupted and list(out) == ["raw"] and list(out.empty) == ["corrected"]
    assert len(captures.load_tracker_stream(out["raw"])) == 5
    assert all(r.stopped for r in fake_recorders)


def test_a_second_ctrl_c_while_saving_does_not_lose_the_recording(fake_recorders, tmp_path, monkeypatch):
    """The first Ctrl-C ends the recording; a second one while the recorders stop and the files are
    written escaped as KeyboardInterrupt and every recording was lost."""
    import os
    import signal
    from trackcal import record

    class SecondCtrlC(FakeRecorder):
        def stop(self):
            super().stop()
            os.kill(os.getpid(), signal.SIGINT)  # the impatient user, while stopping

    def ctrl_c(done, total):
        raise KeyboardInterrupt
    monkeypatch.setattr(record._core, "TrackerRecorder", SecondCtrlC)
    handler = signal.getsignal(signal.SIGINT)
    try:
        out = record_streams({"raw": "Tracker0_raw@tcp://h:1"}, tmp_path / "rec", 3600.0, progress=ctrl_c)
    except KeyboardInterrupt:
        pytest.fail("a second Ctrl-C escaped record_streams: the recording is lost")
    assert out.interrupted and list(out) == ["raw"]
    assert len(captures.load_tracker_stream(out["raw"])) == 5
    assert signal.getsignal(signal.SIGINT) is handler  # Ctrl-C works as before afterwards
    # A device that never connects: the error, and Ctrl-C's handler untouched.
    monkeypatch.setattr(record._core, "TrackerRecorder", FakeRecorder)
    with pytest.raises(RuntimeError, match="no report within"):
        record_streams({"x": "silent@tcp://h:1"}, tmp_path / "none", 1.0, connect_timeout_s=0.05)
    assert signal.getsignal(signal.SIGINT) is handler


def test_ctrl_c_in_trackcal_record_saves_and_exits_130(fake_recorders, tmp_path, monkeypatch, capsys):
    import time as time_module
    import types
    from trackcal import cli, record

    def ctrl_c(seconds):
        raise KeyboardInterrupt
    monkeypatch.setattr(record, "time", types.SimpleNamespace(monotonic=time_module.monotonic, sleep=ctrl_c))
    argv = ["record", "--device", "raw=Tracker0_raw@tcp://h:1", "--duration", "3600",
            "-o", str(tmp_path / "a")]
    try:
        status = cli.main(argv)
    except KeyboardInterrupt:
        pytest.fail("Ctrl-C escaped trackcal record")
    out, err = capsys.readouterr()
    assert status == 130
    assert out == f"raw: wrote {tmp_path / 'a' / 'raw_tracker_stream.csv'}\n"
    assert err == "recording interrupted (Ctrl-C)\n"
    assert len(captures.load_tracker_stream(tmp_path / "a" / "raw_tracker_stream.csv")) == 5
    # Before every device has connected nothing was recorded yet: nothing written, still no traceback.
    argv = ["record", "--device", "x=silent@tcp://h:1", "--duration", "1", "-o", str(tmp_path / "b")]
    assert cli.main(argv) == 130
    assert "before every device had connected: nothing recorded" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()  # made by the command, nothing written: removed again


def _write_reference(path, t, p, q_xyzw):
    rows = ["time,x,y,z,qw,qx,qy,qz"] + [
        f"{float(ti)!r},{float(a)!r},{float(b)!r},{float(c)!r},{float(qi[3])!r},{float(qi[0])!r},"
        f"{float(qi[1])!r},{float(qi[2])!r}" for ti, (a, b, c), qi in zip(t, p, q_xyzw)]
    path.write_text("\n".join(rows) + "\n")


def test_a_recording_is_paired_on_the_lowest_sensor_whatever_reported_first(tmp_path):
    """A live recording of two receivers starts with whichever report the server sent first. The
    reference must be paired with one chosen receiver (``sensor``, default the lowest number), not
    with the sensor of the first row: that paired receiver 2 with receiver 1's reference (395 mm
    'error' on an emulator recording whose raw error was 22.9 mm)."""
    from trackcal import validation
    from trackcal.captures import TrackerStream, save_tracker_stream
    n = 50
    t = 100.0 + 0.01 * np.arange(n)
    p1 = np.column_stack([0.3 + 0.1 * np.sin(t), 0.2 + 0.05 * np.cos(t), np.full(n, -0.5)])
    p2 = p1 + [0.2, -0.3, 0.1]
    q = np.tile([0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8)], (n, 1))
    # Receiver 2 reports first in every cycle, receiver 1 0.1 ms later; receiver 1 is 1 mm off.
    times = np.column_stack([t, t + 1e-4]).ravel()
    sensors = np.tile([2, 1], n)
    positions = np.stack([p2, p1 + [0.001, 0.0, 0.0]], axis=1).reshape(-1, 3)
    quats = np.repeat(q, 2, axis=0)
    raw = tmp_path / "raw_tracker_stream.csv"
    save_tracker_stream(raw, TrackerStream(times, sensors, positions, quats))
    corrected = tmp_path / "corrected_tracker_stream.csv"
    save_tracker_stream(corrected, TrackerStream(times, sensors, positions - np.tile([[0.001, 0.0, 0.0]], (2 * n, 1))
                                                 * (sensors == 1)[:, None], quats))
    reference = tmp_path / "reference_stream.csv"
    # Receiver 1's true pose on the reference clock (offset 0); interpolated at t + 1e-4 it is
    # within 1e-4 * 0.1 m/s of p1, far below the 1 mm offset checked.
    _write_reference(reference, t + 1e-4, np.column_stack([0.3 + 0.1 * np.sin(t + 1e-4),
                                                           0.2 + 0.05 * np.cos(t + 1e-4), np.full(n, -0.5)]), q)
    v = validation.validate_recording(raw, reference, corrected=corrected, time_offset=0.0)
    assert v.capture.origin["sensor"] == 1 and set(v.capture.sensor) == {1}
    # 1 mm raw (to 0.01 mm: interpolation along a 0.1 m/s path over the 0.01 s samples), ~0 corrected.
    np.testing.assert_allclose(v.before.position_mm, 1.0, atol=0.01)
    assert v.after.position_mm.max() < 0.01
    np.testing.assert_allclose(v.before.orientation_deg, 0.0, atol=1e-3)
    # An explicit sensor is paired as asked; one the recording lacks is a ValueError naming the file.
    v2 = validation.validate_recording(raw, reference, time_offset=0.0, sensor=2)
    assert set(v2.capture.sensor) == {2} and v2.before.position_mm.min() > 300
    with pytest.raises(ValueError, match=r"raw_tracker_stream\.csv: no report of sensor 3 \(have: 1, 2\)"):
        validation.validate_recording(raw, reference, time_offset=0.0, sensor=3)
    # 1.5 was paired as sensor 1 (int() truncated it) and reported as the sensor asked for.
    with pytest.raises(ValueError, match=r"sensor 1\.5: must be a whole number"):
        validation.validate_recording(raw, reference, time_offset=0.0, sensor=1.5)


def test_recording_no_device_is_refused_before_anything_is_made(fake_recorders, tmp_path):
    """With no device every device 'had connected' at once: record_streams made the folder, slept
    through the duration and returned an empty recording without a word."""
    out = tmp_path / "rec"
    started = time.monotonic()
    with pytest.raises(ValueError, match="devices: none given"):
        record_streams({}, out, 2.0)
    assert time.monotonic() - started < 1.0 and not out.exists() and not fake_recorders


def test_a_device_whose_server_goes_away_is_reported_after_saving(fake_recorders, tmp_path, monkeypatch):
    """A trackcal-server killed 1.5 s into a 4 s recording: record_streams returned normally and
    `trackcal record` exited 0, the files holding 1.47 s of the 4 s asked for and nothing saying so.
    The client then reports itself disconnected (and reconnects on its own), which is now an error
    naming the device, raised after every recording is saved, as for a device that sent nothing."""
    from trackcal import record

    class Dropping(FakeRecorder):
        polls = 0

        @property
        def connected(self):  # the 'gone' device drops its connection after a few polls
            Dropping.polls += 1
            return not (self.name.startswith("gone") and Dropping.polls > 3)

    monkeypatch.setattr(record._core, "TrackerRecorder", Dropping)
    rec = tmp_path / "rec"
    with pytest.raises(RuntimeError, match=r"lost the connection during the recording to: corrected "
                                           r"\(gone@tcp://h:1\) after [0-9.]+ s of 0\.3 s .*\(saved: .*raw_"
                                           r"tracker_stream\.csv, .*corrected_tracker_stream\.csv\)"):
        record_streams({"raw": "Tracker0_raw@tcp://h:1", "corrected": "gone@tcp://h:1"}, rec, 0.3)
    assert len(captures.load_tracker_stream(rec / "corrected_tracker_stream.csv")) == 5
    assert len(captures.load_tracker_stream(rec / "raw_tracker_stream.csv")) == 5
    # A device that stays connected is not reported.
    Dropping.polls = 0
    out = record_streams({"raw": "Tracker0_raw@tcp://h:1"}, tmp_path / "rec2", 0.3)
    assert list(out) == ["raw"] and out.lost == {}


def test_a_recording_folder_that_cannot_be_made_is_a_value_error(fake_recorders, tmp_path):
    """out_dir naming an existing file (or a folder below one) raised FileExistsError and
    NotADirectoryError out of record_streams; a user's input mistake is a ValueError naming it, as
    `trackcal record -o FILE` says, and the file is left as it was."""
    (tmp_path / "afile").write_text("keep\n")
    for out in (tmp_path / "afile", tmp_path / "afile" / "sub"):
        with pytest.raises(ValueError, match=r"afile.*: cannot make the recording folder"):
            record_streams({"raw": "Tracker0_raw@tcp://h:1"}, out, 0.1)
    assert (tmp_path / "afile").read_text() == "keep\n" and not fake_recorders


def test_a_device_that_goes_quiet_while_connected_is_reported_after_saving(fake_recorders, tmp_path, monkeypatch):
    """A trackcal-server frozen (SIGSTOP; as a pulled network cable) 1.5 s into a 4 s recording
    keeps its TCP connection open, and the client gives it up only after its 10 s liveness timeout:
    record_streams returned normally and `trackcal record` exited 0, the files holding 1.2 s of the
    4 s asked for and nothing saying so. A silence longer than max(1 s, 10 mean intervals) is now an
    error naming the device, raised after every recording is saved."""
    from trackcal import record

    monkeypatch.setattr(record._core, "TrackerRecorder", Arriving)
    rec = tmp_path / "rec"
    # 'frozen' is silent from the start to the end at 2 s (> the 1 s floor by ~1 s, a margin for a
    # loaded machine; its 25 reports make 10 mean intervals 0.8 s); 'raw' grows at every 0.1 s
    # look, so its silences stay far below 1 s.
    with pytest.raises(RuntimeError, match=r"no report for a while during the recording from: corrected "
                                           r"\(frozen@tcp://h:1\) for [0-9.]+ s from [0-9.]+ s of 2 s .*"
                                           r"\(saved: .*raw_tracker_stream\.csv, .*corrected_tracker_stream\.csv\)"):
        record_streams({"raw": "Tracker0_raw@tcp://h:1", "corrected": "frozen@tcp://h:1"}, rec, 2.0)
    raw, frozen = fake_recorders
    assert len(captures.load_tracker_stream(rec / "corrected_tracker_stream.csv")) == frozen.after_start == 25
    assert len(captures.load_tracker_stream(rec / "raw_tracker_stream.csv")) == raw.after_start > 25
    # A device that keeps reporting is not reported.
    out = record_streams({"raw": "Tracker0_raw@tcp://h:1"}, tmp_path / "rec2", 1.5)
    assert list(out) == ["raw"] and out.gaps == {}


@pytest.mark.parametrize("signame", ["SIGTERM", "SIGHUP"])
def test_a_recording_ended_by_sigterm_or_sighup_is_saved_first(server, tmp_path, signame):
    """`kill PID`, `timeout 600 trackcal record ...`, a job scheduler cancelling the job or the
    terminal closing (SIGHUP) killed the process at once: a 60 s recording killed 10 s in left an
    empty folder and nothing of the 10 s (Ctrl-C kept them). Now the reports so far are saved as
    for Ctrl-C, and the signal then takes its usual effect (the process ends by it)."""
    import os
    import signal
    import sys
    out = tmp_path / "rec"
    script = ("import sys\n"
              "from trackcal.record import record_streams\n"
              "def progress(done, total):\n"
              "    if done > 0.5:\n"
              "        print('recording', flush=True)\n"
              f"record_streams({{'raw': 'Tracker0_raw@tcp://127.0.0.1:{server}'}}, {str(out)!r}, 60.0,\n"
              "              progress=progress)\n"
              "print('returned', flush=True)\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline() == "recording\n", proc.stderr.read()
        os.kill(proc.pid, getattr(signal, signame))
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        proc.kill()
    # The signal still ends the process, as it did (the exit status a shell shows: 128 + signal).
    assert proc.returncode == -getattr(signal, signame), stderr
    assert "returned" not in stdout
    raw = captures.load_tracker_stream(out / "raw_tracker_stream.csv")
    # 2 NULL sensors at 100 Hz for > 0.5 s before the signal: >= 100 reports; a third of that on a
    # loaded machine.
    assert len(raw) > 30 and set(raw.sensor) == {1, 2}
    assert not list(out.glob("*.partial")) and not list(out.glob(".*"))


def test_an_ignored_sighup_does_not_end_the_recording(fake_recorders, tmp_path):
    """Under nohup SIGHUP is ignored: the recording goes on to its duration (only a signal that
    would have ended the process ends the recording)."""
    import os
    import signal
    sent = []

    def hang_up(done, total):
        if not sent:
            sent.append(os.kill(os.getpid(), signal.SIGHUP))
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        out = record_streams({"raw": "Tracker0_raw@tcp://h:1"}, tmp_path / "rec", 0.3, progress=hang_up)
        assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, previous)
    assert sent and not out.interrupted and list(out) == ["raw"]


def test_a_file_that_appears_under_a_recordings_name_keeps_both(fake_recorders, tmp_path):
    """Two `trackcal record -o run1` with the same labels (two terminals) both pass the start's check
    that no recording is there; the first to finish writes raw_tracker_stream.csv and the second
    was refused at its save and lost its whole recording (the error said only that the file
    exists). The file that appeared is never replaced; the recording is kept beside it in
    raw_tracker_stream.csv.partial (as trackcal-server --record keeps its own), named by the error."""
    rec = tmp_path / "rec"

    def other_recording(done, total):
        if not (rec / "raw_tracker_stream.csv").exists():
            (rec / "raw_tracker_stream.csv").write_text("the other recording\n")
    with pytest.raises(RuntimeError, match=r"raw_tracker_stream\.csv: exists.*kept in .*raw_tracker_stream\.csv"
                                           r"\.partial.*\(saved: .*raw_tracker_stream\.csv\.partial, "
                                           r".*corrected_tracker_stream\.csv\)"):
        record_streams({"raw": "Tracker0_raw@tcp://h:1", "corrected": "Tracker0@tcp://h:1"}, rec, 0.2,
                       progress=other_recording)
    assert (rec / "raw_tracker_stream.csv").read_text() == "the other recording\n"
    assert len(captures.load_tracker_stream(rec / "raw_tracker_stream.csv.partial")) == 5
    assert len(captures.load_tracker_stream(rec / "corrected_tracker_stream.csv")) == 5


def test_a_recording_against_a_reference_clock_from_zero_estimates_around_a_given_offset(tmp_path):
    """An optical system's clock often counts from its own start, the server's from 1970: the
    offset is then -1.8e9 s, outside the default search (0 +- 0.5 s), and validate_recording used a
    given offset as it was. Known only roughly (the pairing error says to give the difference of
    the starts; the optical system started a little before `trackcal record`), it paired the
    receiver's path with itself 0.3 s later: a 177.6 mm 'raw error' on an emulator recording whose
    true raw error was 0, with no warning. ``estimate_time_offset=True`` searches around the given
    offset, as trackcal.pair does."""
    from trackcal import validation
    from trackcal.captures import TrackerStream, save_tracker_stream
    n = 1500  # 25 s at 60 Hz of a path visiting the same places at different speeds
    t = 1796098746.933219 + np.arange(n) / 60.0
    s = t - t[0]
    p = np.column_stack([0.3 + 0.1 * np.sin(0.9 * s), 0.2 + 0.08 * np.sin(0.37 * s + 1.0), -0.5 + 0.05 * np.cos(0.6 * s)])
    q = np.column_stack([np.zeros(n), np.zeros(n), np.sin(0.1 * s), np.cos(0.1 * s)])
    raw = tmp_path / "raw_tracker_stream.csv"
    save_tracker_stream(raw, TrackerStream(t, np.ones(n, dtype=int), p, q))
    true_offset = 1.3 - 1796098746.0  # the optical clock started 1.3 s before the recording's second
    reference = tmp_path / "reference_stream.csv"
    _write_reference(reference, t + true_offset, p, q)
    rough = 1.0 - 1796098746.0  # 0.3 s off
    v = validation.validate_recording(raw, reference, time_offset=rough, estimate_time_offset=True)
    assert v.capture.origin["time_offset_source"] == "estimated"
    # The paired path is the reference's own: the offset comes back to interpolation error (the
    # path moves at <= 0.1 m/s; 1 ms is 0.1 mm) and the raw error to ~0.
    assert abs(v.capture.origin["time_offset_s"] - true_offset) < 1e-3
    assert v.tables[-1].before_position_mm["mean"] < 0.1
    # Given and not estimated (the default with an offset), it is used as it is.
    given = validation.validate_recording(raw, reference, time_offset=rough)
    assert given.capture.origin["time_offset_source"] == "given"
    assert given.capture.origin["time_offset_s"] == rough
    # No offset: estimated around 0, as before; asking for no estimate without an offset is refused.
    with pytest.raises(ValueError, match="estimate_time_offset=False needs a time_offset"):
        validation.validate_recording(raw, reference, estimate_time_offset=False)


def test_an_ignored_sighup_while_saving_does_not_mark_the_recording_interrupted(fake_recorders, tmp_path,
                                                                                   monkeypatch):
    """Under nohup SIGHUP is ignored. While the recorders stop and the files are saved the handlers
    are replaced to defer Ctrl-C, SIGTERM and SIGHUP; an ignored SIGHUP was replaced too, so a
    terminal closed at that moment marked a full-length recording 'interrupted' (trackcal record
    then said 'recording interrupted (Ctrl-C)', exit 130, and its lost-connection and gap checks
    were skipped). An ignored signal stays ignored throughout."""
    import os
    import signal
    from trackcal import record

    class HangUpWhileStopping(FakeRecorder):
        def stop(self):
            super().stop()
            os.kill(os.getpid(), signal.SIGHUP)  # the terminal closes while the recording is saved
    monkeypatch.setattr(record._core, "TrackerRecorder", HangUpWhileStopping)
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        out = record_streams({"raw": "Tracker0_raw@tcp://h:1"}, tmp_path / "rec", 0.2)
        assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, previous)
    assert HangUpWhileStopping.instances[0].stopped
    assert not out.interrupted and list(out) == ["raw"]


def test_a_gap_before_an_interruption_is_judged_on_the_time_recorded(fake_recorders, tmp_path, monkeypatch):
    """A silence is a gap when longer than max(1 s, 10 mean intervals between reports). The mean
    was taken over the duration asked for, also when Ctrl-C ended the recording early: stopped
    2 s into an hour, 25 reports made the mean interval 144 s instead of 0.08 s, and a device frozen
    for the whole 2 s was no gap. It is the time recorded."""
    from trackcal import record
    monkeypatch.setattr(record._core, "TrackerRecorder", Arriving)

    def ctrl_c_after_2_s(done, total):
        if done > 2.0:
            raise KeyboardInterrupt
    out = record_streams({"raw": "Tracker0_raw@tcp://h:1", "corrected": "frozen@tcp://h:1"}, tmp_path / "rec",
                         3600.0, progress=ctrl_c_after_2_s)
    assert out.interrupted
    # 'frozen' sent its 25 reports at the start and nothing for the ~2 s after (the 1 s floor,
    # with ~1 s of margin for a loaded machine); 'raw' grew at every 0.1 s look.
    assert list(out.gaps) == ["corrected"]
    start, length = out.gaps["corrected"]
    assert start < 0.5 and length > 1.5


def test_a_recording_whose_partial_file_exists_is_refused_before_it_records(fake_recorders, tmp_path):
    """LABEL_tracker_stream.csv.partial holds a recording kept beside a file that appeared under its
    name (a second `trackcal record` into the folder). A third one under that name was refused at
    its save for both names and lost its whole recording, the error saying only that the file
    exists. A .partial is now a recording like the finished file: refused before anything is
    recorded, and left as it was."""
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "raw_tracker_stream.csv.partial").write_text("the second recording\n")

    def first_recording_ends(done, total):
        if not (rec / "raw_tracker_stream.csv").exists():
            (rec / "raw_tracker_stream.csv").write_text("the first recording\n")
    with pytest.raises(ValueError, match=r"raw_tracker_stream\.csv\.partial: exists .*never overwritten"):
        record_streams({"raw": "Tracker0_raw@tcp://h:1"}, rec, 0.2, progress=first_recording_ends)
    assert (rec / "raw_tracker_stream.csv.partial").read_text() == "the second recording\n"
    assert not fake_recorders  # refused before any device was contacted


def test_a_recording_goes_to_disk_as_it_records_in_the_format_of_one_write(fake_recorders, tmp_path,
                                                                           monkeypatch):
    """Every report was held in memory until the end and written then: ~330 MB held for an hour of
    4 sensors at 120 Hz raw and corrected, ~1.2 GB at the save, and all of it lost to a SIGKILL, the
    OOM killer or a crash. The rows are now appended to LABEL_tracker_stream.csv.partial at least
    every second and the file is moved to its name at the end, byte for byte the file one write of
    all the rows gives."""
    from trackcal import record
    from trackcal.captures import TrackerStream, save_tracker_stream
    monkeypatch.setattr(record._core, "TrackerRecorder", Arriving)
    rec = tmp_path / "rec"
    on_disk = []

    def look(done, total):
        if done > 1.5 and not on_disk:  # after the first flush (1 s), before the end
            on_disk.append(len(captures.load_tracker_stream(rec / "raw_tracker_stream.csv.partial")))
            on_disk.append(fake_recorders[0].taken - fake_recorders[0].first)
    out = record_streams({"raw": "Tracker0_raw@tcp://h:1"}, rec, 2.5, progress=look)
    assert list(out) == ["raw"] and out.gaps == {}
    # Written while recording: every report taken from the recorder is in the file.
    written, taken = on_disk
    assert written == taken > 0
    assert fake_recorders[0].takes >= 3  # the start, a flush, the end
    one_write = tmp_path / "one_write.csv"
    r = fake_recorders[0]
    all_rows = Arriving("x")
    all_rows.taken, all_rows.arrived = r.first, r.taken
    d = all_rows.take()
    save_tracker_stream(one_write, TrackerStream(d["time"], d["sensor"] + 1, d["positions"], d["quaternions_xyzw"]))
    assert (rec / "raw_tracker_stream.csv").read_bytes() == one_write.read_bytes()
    assert sorted(p.name for p in rec.iterdir()) == ["raw_tracker_stream.csv"]


def test_a_killed_recording_keeps_its_rows_up_to_the_last_second(server, tmp_path):
    """SIGKILL (the OOM killer, a crash) cannot be caught: the rows written so far stay in
    LABEL_tracker_stream.csv.partial, a tracker stream file, and the label is refused until it is
    moved away."""
    import os
    import signal
    import sys
    out = tmp_path / "rec"
    script = ("from trackcal.record import record_streams\n"
              "def progress(done, total):\n"
              "    if done > 2.5:\n"
              "        print('recording', flush=True)\n"
              f"record_streams({{'raw': 'Tracker0_raw@tcp://127.0.0.1:{server}'}}, {str(out)!r}, 60.0,\n"
              "              progress=progress)\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline() == "recording\n", proc.stderr.read()
        os.kill(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=30)
    finally:
        proc.kill()
    raw = captures.load_tracker_stream(out / "raw_tracker_stream.csv.partial")
    # 2 NULL sensors at 100 Hz, flushed at 1 s and 2 s (2.5 s in when killed): >= 200 rows; a
    # third of that on a loaded machine.
    assert len(raw) > 60 and set(raw.sensor) == {1, 2}
    assert not (out / "raw_tracker_stream.csv").exists()
    with pytest.raises(ValueError, match=r"raw_tracker_stream\.csv\.partial: exists \(a recording killed"):
        record_streams({"raw": f"Tracker0_raw@tcp://127.0.0.1:{server}"}, out, 0.1)


def test_ctrl_c_during_a_flush_keeps_the_reports_it_took(fake_recorders, tmp_path, monkeypatch):
    """Reports taken from the recorder and not yet written are in no file: Ctrl-C (or SIGTERM)
    arriving then waits until they are written, then ends the recording as anywhere else."""
    import os
    import signal
    from trackcal import record

    class CtrlCWhileFlushing(Arriving):
        def take(self):
            d = super().take()
            if self.takes == 2:  # the first flush, 1 s in
                os.kill(os.getpid(), signal.SIGINT)
            return d
    monkeypatch.setattr(record._core, "TrackerRecorder", CtrlCWhileFlushing)
    out = record_streams({"raw": "Tracker0_raw@tcp://h:1"}, tmp_path / "rec", 3600.0)
    assert out.interrupted and list(out) == ["raw"]
    assert len(captures.load_tracker_stream(out["raw"])) == fake_recorders[0].after_start > 0


def test_a_report_the_capture_writer_refuses_costs_that_report_only(fake_recorders, tmp_path, monkeypatch):
    """A report with a non-finite value (a driver's bad record, passed on by the server) made the
    save at the end refuse the whole file: an hour of recording lost for one row, the error naming
    record 2 of nothing that was written. The other rows are recorded; the error says how many
    reports were left out and why, naming the recording."""
    from trackcal import record

    class OneBadReport(Arriving):
        def take(self):
            d = super().take()
            if self.takes == 2 and len(d["time"]) > 3:  # the reports after the start
                d["positions"][2, 0] = np.nan
            return d
    monkeypatch.setattr(record._core, "TrackerRecorder", OneBadReport)
    rec = tmp_path / "rec"
    with pytest.raises(RuntimeError, match=r"raw_tracker_stream\.csv: 1 report left out \(the first, report 2 "
                                           r"of the recording: column x: nan is not a finite number\)"):
        record_streams({"raw": "Tracker0_raw@tcp://h:1"}, rec, 0.3)
    raw = captures.load_tracker_stream(rec / "raw_tracker_stream.csv")
    assert len(raw) == fake_recorders[0].after_start - 1 > 0
    assert sorted(p.name for p in rec.iterdir()) == ["raw_tracker_stream.csv"]


def test_a_refused_report_after_a_repeat_in_its_take_is_numbered_in_the_recording(fake_recorders, tmp_path,
                                                                                     monkeypatch):
    """The repeats of a take are left out before the capture writer sees it, and the writer's first
    refusal was numbered in what was left: a take of (a report, its time again, a report with a NaN)
    named the NaN "report 1", which is the repeat. Both errors number the reports as they came."""
    from trackcal import record

    class RepeatThenBad(Arriving):
        def take(self):
            d = super().take()
            if self.takes == 2 and len(d["time"]) > 3:  # the reports after the start
                d["time"][1], d["sensor"][1] = d["time"][0], d["sensor"][0]  # report 1 repeats report 0
                d["positions"][2, 0] = np.nan  # report 2 is refused by the writer
            return d
    monkeypatch.setattr(record._core, "TrackerRecorder", RepeatThenBad)
    rec = tmp_path / "rec"
    with pytest.raises(RuntimeError) as e:
        record_streams({"raw": "Tracker0_raw@tcp://h:1"}, rec, 0.3)
    assert "1 report left out (the first, report 2 of the recording: column x: nan is not a finite number)" \
        in str(e.value)
    assert "1 report left out (the first, report 1 of the recording: time " in str(e.value)
    raw = captures.load_tracker_stream(rec / "raw_tracker_stream.csv")
    assert len(raw) == fake_recorders[0].after_start - 2 > 0


def test_an_error_that_ends_a_recording_leaves_its_rows_in_the_partial_file(fake_recorders, tmp_path,
                                                                             monkeypatch):
    """An exception other than an interruption (here from the progress callback) ends the
    recording without saving it. The rows already written stay in LABEL_tracker_stream.csv.partial
    (removing an open .partial is only for one that holds no row)."""
    from trackcal import record
    monkeypatch.setattr(record._core, "TrackerRecorder", Arriving)
    rec = tmp_path / "rec"

    def fails_after_a_flush(done, total):
        if done > 1.5:
            raise RuntimeError("the progress display failed")
    with pytest.raises(RuntimeError, match="the progress display failed"):
        record_streams({"raw": "Tracker0_raw@tcp://h:1"}, rec, 3600.0, progress=fails_after_a_flush)
    r = fake_recorders[0]
    assert len(captures.load_tracker_stream(rec / "raw_tracker_stream.csv.partial")) == r.after_start > 0
    assert r.stopped


def test_the_rows_are_formatted_without_a_scratch_folder(fake_recorders, tmp_path, monkeypatch):
    """Every flush wrote its rows to a file in a folder under /tmp (tempfile.TemporaryDirectory,
    made for the whole recording) and read them back: a SIGKILL left the folder there, a /tmp on
    another (or a full) file system failed the recording, and the round trip halved the writer's
    speed. The rows are formatted in memory by the capture writer's C++ (format_tracker_stream)."""
    import tempfile
    from trackcal import record
    monkeypatch.setattr(record._core, "TrackerRecorder", Arriving)
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    seen = []
    out = record_streams({"raw": "Tracker0_raw@tcp://h:1"}, tmp_path / "rec", 1.3,
                         progress=lambda done, total: seen.extend(p.name for p in scratch.iterdir()))
    assert list(out) == ["raw"] and seen == []
    assert len(captures.load_tracker_stream(out["raw"])) == fake_recorders[0].after_start > 0


def test_format_tracker_stream_gives_the_bytes_of_the_file(tmp_path):
    """format_tracker_stream is save_tracker_stream without the file: the same bytes, the rows alone
    without the header (appended, they make the file of one write), the same refusals naming
    ``name`` where the writer names the file."""
    from trackcal.captures import TrackerStream, format_tracker_stream, save_tracker_stream
    rng = np.random.default_rng(7)
    n = 40
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    stream = TrackerStream(1796098746.0 + np.arange(n) / 120.0, 1 + np.arange(n) % 2, rng.normal(size=(n, 3)), q)
    save_tracker_stream(tmp_path / "one.csv", stream)
    whole = (tmp_path / "one.csv").read_bytes()
    assert format_tracker_stream(stream) == whole
    first = TrackerStream(stream.time[:9], stream.sensor[:9], stream.positions[:9], stream.quaternions_xyzw[:9])
    rest = TrackerStream(stream.time[9:], stream.sensor[9:], stream.positions[9:], stream.quaternions_xyzw[9:])
    assert format_tracker_stream(first) + format_tracker_stream(rest, header=False) == whole
    bad = TrackerStream(stream.time[:3], stream.sensor[:3], stream.positions[:3].copy(), stream.quaternions_xyzw[:3])
    bad.positions[1, 2] = np.inf
    with pytest.raises(ValueError, match=r"^raw\.partial: record 1: column z: inf is not a finite number$"):
        format_tracker_stream(bad, name="raw.partial", header=False)


def test_a_recording_killed_while_it_waits_for_the_first_report_leaves_no_partial_file(tmp_path):
    """The .partial files were made before the wait for every device's first report: a recording
    killed then (SIGKILL; a server not up yet, a typo in its address) left LABEL_tracker_stream.csv
    .partial holding only the header, and every later recording with the label was refused ("a
    recording killed before it ended"). They are made when the first reports have come."""
    import os
    import signal
    import sys
    out = tmp_path / "rec"
    script = ("from trackcal.record import record_streams\n"
              f"record_streams({{'raw': 'Tracker0_raw@tcp://127.0.0.1:{free_port()}'}}, {str(out)!r}, 1.0,\n"
              "              connect_timeout_s=30.0)\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 30.0  # the import and the folder: well below on a loaded machine
        while not out.exists() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert out.exists(), proc.stderr.read() if proc.poll() is not None else "no folder after 30 s"
        time.sleep(0.5)  # into the wait (nothing listens on the port: it lasts 30 s)
        assert proc.poll() is None
        os.kill(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert list(out.iterdir()) == []


def test_a_partial_file_made_during_the_wait_is_refused_and_left_alone(fake_recorders, tmp_path, monkeypatch):
    """Made when the first reports have come, the .partial can be taken in between by another
    recording into the folder: its file is refused (ValueError naming it) and left as it was, and
    the devices are let go."""
    from trackcal import record
    rec = tmp_path / "rec"

    class AnotherRecordingStarts(FakeRecorder):
        def __len__(self):
            (rec / "raw_tracker_stream.csv.partial").write_text("the other recording\n")
            return super().__len__()
    monkeypatch.setattr(record._core, "TrackerRecorder", AnotherRecordingStarts)
    with pytest.raises(ValueError, match=r"raw_tracker_stream\.csv\.partial: exists .*never overwritten"):
        record_streams({"raw": "Tracker0_raw@tcp://h:1"}, rec, 0.2)
    assert (rec / "raw_tracker_stream.csv.partial").read_text() == "the other recording\n"
    assert all(r.stopped for r in fake_recorders)


def test_the_wait_for_the_first_report_says_so_after_a_second(fake_recorders, tmp_path, capsys):
    """`trackcal record` waited silently for the first reports, up to --connect-timeout (a server
    resetting its Fastrak takes ~7 s): it looked hung. After 1 s it prints one line naming the
    devices still silent; ``waiting`` redirects it (a callable given the line) or silences it (None)."""
    lines = []
    with pytest.raises(RuntimeError, match="no report within 1.5 s"):
        record_streams({"raw": "Tracker0_raw@tcp://h:1", "x": "silent@tcp://h:2"}, tmp_path / "a", 0.1,
                       connect_timeout_s=1.5, waiting=lines.append)
    assert lines == ["waiting up to 1.5 s for the first report from: x (silent@tcp://h:2)"]
    with pytest.raises(RuntimeError, match="no report within 1.2 s"):
        record_streams({"x": "silent@tcp://h:2"}, tmp_path / "a", 0.1, connect_timeout_s=1.2)
    assert capsys.readouterr().err == "waiting up to 1.2 s for the first report from: x (silent@tcp://h:2)\n"
    with pytest.raises(RuntimeError, match="no report within 1.2 s"):
        record_streams({"x": "silent@tcp://h:2"}, tmp_path / "a", 0.1, connect_timeout_s=1.2, waiting=None)
    assert capsys.readouterr().err == ""
    # Devices that report at once: no line.
    record_streams({"raw": "Tracker0_raw@tcp://h:1"}, tmp_path / "b", 0.1, waiting=lines.append)
    assert len(lines) == 1


def test_the_partial_file_is_synced_to_disk_while_it_records(fake_recorders, tmp_path, monkeypatch):
    """The rows appended every second stayed in the page cache until the end (fsync only at the
    save): a power cut or a kernel crash an hour in could lose the whole recording, which the
    .partial is there to keep. The .partial (and, once, its folder) is now fsynced every 5 s."""
    import os
    from trackcal import record
    monkeypatch.setattr(record._core, "TrackerRecorder", Arriving)
    monkeypatch.setattr(record, "_FSYNC_S", 0.2)  # in place of 5 s, to keep the test short
    real_fsync = os.fsync
    synced = []

    def fsync(fd):
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        real_fsync(fd)
    monkeypatch.setattr(os, "fsync", fsync)
    rec = tmp_path / "rec"
    while_recording = []

    def look(done, total):
        if done > 1.4 and not while_recording:  # after the first flush (1 s) and the sync after it
            while_recording.extend(synced)
    out = record_streams({"raw": "Tracker0_raw@tcp://h:1"}, rec, 1.8, progress=look)
    assert list(out) == ["raw"]
    assert str(rec / "raw_tracker_stream.csv.partial") in while_recording
    assert str(rec) in while_recording


class TypoHostRecorder(FakeRecorder):
    """A device named Typo* whose host name ('traker.lab') does not resolve: it never connects and
    sends nothing; the others report as FakeRecorder does."""
    connected, pong_received = False, False
    host = "traker.lab"

    @property
    def host_unknown(self):
        return self.name.startswith("Typo")

    def __len__(self):
        return 0 if self.name.startswith("Typo") else super().__len__()


def test_an_unknown_host_name_is_named_as_such(fake_recorders, tmp_path, monkeypatch):
    """A mistyped host name ('traker.lab') said "no connection; is a server running at that
    address?", sending the user to check a server that was fine. The client knows the name did not
    resolve (TrackerRecorder.host_unknown), and the error names the host."""
    from trackcal import record

    monkeypatch.setattr(record._core, "TrackerRecorder", TypoHostRecorder)
    with pytest.raises(RuntimeError, match=r"^no report from: raw \(Typo@tcp://traker\.lab:3883: "
                                           r"unknown host 'traker\.lab' \(the name does not resolve to an "
                                           r"address: a typo, or no DNS\?\)\)$"):
        record_streams({"raw": "Typo@tcp://traker.lab:3883", "ok": "Tracker0@tcp://h:1"}, tmp_path / "rec", 0.1,
                       connect_timeout_s=0.1)


def test_an_unknown_host_fails_at_once_not_after_the_connect_timeout(fake_recorders, tmp_path, monkeypatch, capsys):
    """A host name that does not resolve waited out the whole connect timeout (10 s by default, as
    long as the user asked for) before failing, though the client knew at once that no server can
    be reached under that name. The recording fails as soon as the look-up has failed, naming the
    host, and `trackcal record` does not suggest a longer --connect-timeout for it."""
    from trackcal import cli, record

    monkeypatch.setattr(record._core, "TrackerRecorder", TypoHostRecorder)
    begun = time.monotonic()
    with pytest.raises(record.NoFirstReport, match=r"^no report from: raw \(Typo@tcp://traker\.lab:3883: unknown "
                                                    r"host 'traker\.lab' \(the name does not resolve to an address: "
                                                    r"a typo, or no DNS\?\)\)$"):
        record_streams({"raw": "Typo@tcp://traker.lab:3883", "ok": "Tracker0@tcp://h:1"}, tmp_path / "rec", 0.1,
                       connect_timeout_s=30)
    # 5 s: far below the 30 s timeout, far above the 20 ms polling step on a loaded machine.
    assert time.monotonic() - begun < 5
    assert not (tmp_path / "rec").exists()
    assert cli.main(["record", "--device", "raw=Typo@tcp://traker.lab:3883", "--duration", "1",
                     "--connect-timeout", "30", "-o", str(tmp_path / "rec")]) != 0
    err = capsys.readouterr().err
    assert "unknown host 'traker.lab'" in err and "--connect-timeout" not in err


def test_a_time_a_sensor_already_had_is_left_out_and_told_and_the_recording_loads(fake_recorders, tmp_path,
                                                                                   monkeypatch):
    """A server whose clock did not tick between two reports of a sensor (or stepped back onto a time
    it had given), or a report sent twice, gave one sensor's time twice: the recording was saved and
    then failed to load ("time ... of sensor 1 repeats line ..."), all of it lost to the tools. Such a
    report is left out (the file holds one sample per sensor and time, and always loads), and the
    error after saving says how many and the first: nothing is lost silently. A time earlier than the
    sensor's last but new (a clock stepped back) is kept: it loses nothing, and the pairing names the
    order (docs/captures.md)."""
    from trackcal import record

    class Repeating(Arriving):
        previous_last, repeats, back = None, 0, 0

        def take(self):
            d = super().take()
            n = len(d["time"])
            if self.takes < 2 or n < 2:  # the first take is the synchronised start (not written)
                return d
            def rows(first, last, shift=0.0):
                return {k: v[first:last] + (shift if k == "positions" else 0) for k, v in d.items()}
            # The first report again with another pose (a clock that did not tick), the previous
            # take's last report again (already on disk), and a new time 1 s back (a clock stepped back).
            parts = [rows(0, 1), rows(0, 1, 0.5), rows(1, n)]
            self.repeats += 1
            if self.previous_last is not None:
                parts.insert(0, {k: v + (0.5 if k == "positions" else 0) for k, v in self.previous_last.items()})
                self.repeats += 1
            back = rows(n - 1, n)
            back["time"] = back["time"] - 1.0
            parts.append(back)
            self.back += 1
            self.previous_last = rows(n - 1, n)
            return {k: np.concatenate([p[k] for p in parts]) for k in d}
    monkeypatch.setattr(record._core, "TrackerRecorder", Repeating)
    rec = tmp_path / "rec"
    # 2.3 s: the reports go to disk in three takes (flushes at 1 s and 2 s, and the end), so repeats
    # within a take and across takes (already on disk) are both seen.
    with pytest.raises(RuntimeError, match=r"raw_tracker_stream\.csv: [0-9]+ reports left out \(the first, report 1 "
                                           r"of the recording: time [0-9.]+ of sensor [12] repeats an earlier "
                                           r"report's \(one sample per sensor and time"):
        record_streams({"raw": "Tracker0_raw@tcp://h:1"}, rec, 2.3)
    fake = fake_recorders[0]
    assert fake.takes >= 4 and fake.repeats >= 3
    raw = captures.load_tracker_stream(rec / "raw_tracker_stream.csv")
    # The repeats, and the previous take's last report given again (already on disk), are left out;
    # the new times 1 s back are kept.
    assert len(raw) == fake.after_start + fake.back
    np.testing.assert_array_less(raw.positions[:, 0], 0.5)  # no repeated report's pose was written


def test_the_repeat_check_agrees_with_every_time_kept_across_takes_with_clock_steps(tmp_path):
    """_StreamFile leaves out a report at a time its sensor already had, in its take or any before,
    and keeps every other (a new time earlier than the latest too). Takes of two sensors with
    in-order runs, a clock that does not tick, reports sent twice and clocks stepped back (onto
    times given and between them), seed fixed, against a set of every kept (sensor, time)."""
    from trackcal import record
    rng = np.random.default_rng(20261202)
    f = record._StreamFile(tmp_path / "raw_tracker_stream.csv")
    kept_times, latest, backwards_kept = set(), {}, 0
    clock = {1: 100.0, 2: 100.0}
    for take in range(60):
        times, sensors = [], []
        for _ in range(int(rng.integers(1, 12))):
            s = int(rng.integers(1, 3))
            kind = rng.random()
            if kind < 0.55:  # in order
                clock[s] += 0.25
            elif kind < 0.7:  # the clock did not tick
                pass
            elif kind < 0.85:  # stepped back onto a time given (quarter seconds)
                clock[s] = max(100.0, clock[s] - 0.25 * int(rng.integers(1, 9)))
            else:  # stepped back between the times given
                clock[s] -= 0.125 + 0.25 * int(rng.integers(0, 4))
            times.append(clock[s])
            sensors.append(s)
        n = len(times)
        q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        stream = record.TrackerStream(np.array(times), np.array(sensors, dtype=np.int32), np.zeros((n, 3)), q)
        expected = []
        for s, t in zip(sensors, times):
            expected.append((s, t) not in kept_times)
            kept_times.add((s, t))
        out, numbers = f._without_repeats(stream)
        assert [i in set(numbers.tolist()) for i in range(n)] == expected, f"take {take}"
        for s, t, e in zip(sensors, times, expected):
            backwards_kept += e and t < latest.get(s, -np.inf)
            latest[s] = max(latest.get(s, -np.inf), t)
        assert out.time.tolist() == [t for t, e in zip(times, expected) if e]
    # Each kind happened: some left out, and some kept before their sensor's latest time.
    assert f.repeated > 20 and backwards_kept > 20
    f.discard()
