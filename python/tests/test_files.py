"""trackcal._files: the atomic writers of every Python output."""

import errno
import os
import stat
import threading

import pytest

from trackcal import _files


def test_writers_give_the_umask_mode_without_changing_the_process_umask(tmp_path, monkeypatch):
    """The umask can only be read by setting it: the writers set it to 0 and back for every file,
    and a file any other thread of the process created meanwhile (a C++ writer running without the
    GIL) was world-writable. They now create their temporary file as open(O_CREAT | O_EXCL, 0o666)
    does any file, and never touch the umask."""
    calls = []
    real_umask = os.umask
    monkeypatch.setattr(os, "umask", lambda mask: calls.append(mask) or real_umask(mask))
    old = real_umask(0o027)
    try:
        new = _files.write_new(tmp_path / "new.csv", b"a\n")
        replaced = _files.replace_atomically(tmp_path / "report.html", b"b\n")
        _files.replace_atomically(replaced, b"c\n")
        current = real_umask(0o027)
    finally:
        real_umask(old)
    assert calls == [], f"the process umask was set to {calls} while writing"
    assert current == 0o027
    assert stat.S_IMODE(new.stat().st_mode) == 0o640
    assert stat.S_IMODE(replaced.stat().st_mode) == 0o640
    assert new.read_bytes() == b"a\n" and replaced.read_bytes() == b"c\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.csv", "report.html"]  # no temporaries


def test_write_new_never_replaces_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "poses.csv"
    target.write_bytes(b"precious")
    with pytest.raises(ValueError, match=r"poses\.csv: exists; refusing to overwrite it"):
        _files.write_new(target, b"other")
    assert target.read_bytes() == b"precious"
    assert [p.name for p in tmp_path.iterdir()] == ["poses.csv"]
    # Many writers at once: one wins, the others are refused, no temporary is left.
    errors = []

    def write(i):
        try:
            _files.write_new(tmp_path / "race.csv", str(i).encode())
        except ValueError as e:
            errors.append(str(e))

    threads = [threading.Thread(target=write, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(errors) == 7
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.csv", "race.csv"]


def test_a_failed_write_names_the_file_asked_for_and_leaves_nothing(tmp_path, monkeypatch):
    """A folder that refuses the temporary file (read-only, or a name too long once '.tmp-XXXXXXXX'
    is added) named only the temporary file, and a full disk no file at all: the error names the
    file asked for, as the C++ writers do, and keeps its errno."""
    long_name = tmp_path / ("r" * 240 + ".csv")  # a valid name; its temporary's is too long
    for write in (_files.write_new, _files.replace_atomically):
        with pytest.raises(OSError) as e:
            write(long_name, b"data")
        assert e.value.filename == str(long_name)
        assert str(e.value.strerror).startswith(f"cannot create a temporary file in {tmp_path}: ")
        assert e.value.errno == errno.ENAMETOOLONG
    assert list(tmp_path.iterdir()) == []

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    target = tmp_path / "residuals.csv"
    for write in (_files.write_new, _files.replace_atomically):
        with pytest.raises(OSError) as e:
            write(target, b"data")
        assert e.value.filename == str(target)
        assert e.value.strerror == "write failed: No space left on device"
        assert e.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []


def test_replacing_writes_through_a_symlink_and_keeps_it(tmp_path):
    """A report or history kept in a dated folder and reached through a link (latest.html ->
    runs/12-01/report.html) was replaced by a regular file: the rename put the new file in place of
    the link, and the file it led to kept the old contents. Written through the link, as the C++
    writer (core/file_util.cc) and any editor do."""
    (tmp_path / "runs").mkdir()
    target = tmp_path / "runs" / "report.html"
    target.write_bytes(b"old")
    (tmp_path / "latest.html").symlink_to("runs/report.html")           # relative
    (tmp_path / "current.html").symlink_to(tmp_path / "latest.html")    # a chain
    for link in ("latest.html", "current.html"):
        _files.replace_atomically(tmp_path / link, f"new through {link}".encode())
        assert (tmp_path / link).is_symlink()
        assert target.read_bytes() == f"new through {link}".encode()
    assert os.readlink(tmp_path / "latest.html") == "runs/report.html"
    # A link to a file not written yet creates it.
    (tmp_path / "next.html").symlink_to("runs/next.html")
    _files.replace_atomically(tmp_path / "next.html", b"first")
    assert (tmp_path / "next.html").is_symlink() and (tmp_path / "runs" / "next.html").read_bytes() == b"first"
    assert not [p for p in tmp_path.rglob("*") if ".tmp-" in p.name]
    # write_new still refuses a link, dangling or not: it is an existing name.
    with pytest.raises(ValueError, match="exists"):
        _files.write_new(tmp_path / "latest.html", b"x")


def test_replacing_keeps_the_mode_of_the_file_replaced(tmp_path):
    """As the C++ writer does: a history or report made group-writable (0664) for a lab, or private
    (0600), got the umask's mode on every rewrite."""
    path = tmp_path / "history.jsonl"
    old = os.umask(0o022)
    try:
        for mode in (0o664, 0o600):
            _files.replace_atomically(path, b"first")
            os.chmod(path, mode)
            _files.replace_atomically(path, b"second")
            assert stat.S_IMODE(path.stat().st_mode) == mode
            assert path.read_bytes() == b"second"
    finally:
        os.umask(old)
