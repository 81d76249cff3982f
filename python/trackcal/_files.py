"""Writing output files atomically.

write_new: files that must never replace an existing one (a capture, a recording, residuals). The
data goes to a temporary file in the target's folder, is synced, and is then hard-linked to the
target: link() fails when the target exists, however late another file appeared there, where a
check followed by a rename would replace it. The C++ writers (core/capture.cc, WriteFileAtomically)
publish the same way.

replace_atomically: files trackcal owns and rewrites (history.jsonl, a report, its figures), after
the caller has decided the target may be replaced: a reader sees the old or the new file, never
half of one.

Both give the file the mode any new file gets under the umask (mkstemp makes it owner-only),
without changing the process's umask.
"""

from __future__ import annotations

import errno
import os
import pathlib
import secrets
import stat

# link() errors that mean the file system has no hard links (FAT, some network and FUSE mounts).
_NO_HARD_LINKS = {errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS, errno.EMLINK}


def write_new(path, data: bytes, exists_message: str = "exists; refusing to overwrite it") -> pathlib.Path:
    """Writes ``data`` to the new file ``path`` atomically. ValueError "<path>: <exists_message>"
    when path exists, and a ValueError saying so when the file system cannot hard-link (the file
    is then not written: no fallback could guarantee that nothing is replaced)."""
    path = pathlib.Path(path)
    if not path.parent.is_dir():  # else the error would name the temporary file
        raise ValueError(f"{path}: {path.parent} is not an existing folder")
    tmp = _synced_temporary(path, data)
    try:
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise ValueError(f"{path}: {exists_message}") from None
        except OSError as e:
            if e.errno in _NO_HARD_LINKS:
                raise ValueError(f"{path}: not written: the file system of {path.parent} has no hard links "
                                 f"({e.strerror}), which trackcal needs to write a file without risking "
                                 "replacing another; write it to another folder") from None
            raise
    finally:
        os.unlink(tmp)
    return path


def _synced_temporary(path: pathlib.Path, data: bytes) -> str:
    """Name of a new temporary file ".<name>.tmp-XXXXXX" next to ``path`` holding ``data``, synced,
    with the mode the umask gives any new file. Created as core/file_util.cc creates its own, by
    open(O_CREAT | O_EXCL, 0o666): mkstemp's 0600 had to be widened with the umask, read by setting
    it to 0 and back, which is process-wide: a file another thread created meanwhile (a C++ writer
    running without the GIL) was world-writable."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    # A failure names the file asked for: a read-only folder named only the temporary
    # ".poses.csv.tmp-1a2b3c4d", and a full disk no file at all ("[Errno 28] No space left on
    # device"), as the C++ writers' "<path>: cannot create a temporary file in <folder>" do not.
    for _ in range(100):
        tmp = str(path.parent / f".{path.name}.tmp-{secrets.token_hex(4)}")
        try:
            fd = os.open(tmp, flags, 0o666)
            break
        except FileExistsError:
            continue
        except OSError as e:
            raise OSError(e.errno, f"cannot create a temporary file in {path.parent}: {e.strerror}",
                          str(path)) from None
    else:
        raise FileExistsError(errno.EEXIST, "no free temporary name", str(path.parent / f".{path.name}.tmp-*"))
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    except OSError as e:
        os.unlink(tmp)
        raise OSError(e.errno, f"write failed: {e.strerror}", str(path)) from None
    except BaseException:
        os.unlink(tmp)
        raise
    return tmp


def replace_atomically(path, data: bytes) -> pathlib.Path:
    """Writes ``data`` to ``path`` by a rename over it (see the module comment): the caller decides
    that an existing ``path`` may be replaced. A symbolic link is written through and kept; the file
    replaced keeps its mode. Returns ``path`` as given."""
    given = path = pathlib.Path(path)
    # A symbolic link is written through and kept (latest.html -> runs/12-01/report.html): renamed
    # over the link, the new file replaced the link and the file it led to kept the old contents.
    # A link to a file not made yet leads to where it will be; a loop is the OSError it is.
    if path.is_symlink():
        path = pathlib.Path(os.path.realpath(path, strict=False))
        if path.is_symlink():
            raise OSError(errno.ELOOP, os.strerror(errno.ELOOP), str(given))
    if not path.parent.is_dir():  # else the error would name the temporary file
        raise ValueError(f"{given}: {path.parent} is not an existing folder")
    tmp = _synced_temporary(path, data)
    try:
        # The file replaced passes its mode on (a lab's group-writable 0664 history, a private
        # 0600 report), as the C++ writer's does; a new file has the umask's.
        try:
            st = os.stat(path)
        except FileNotFoundError:
            st = None
        if st is not None and stat.S_ISREG(st.st_mode):
            os.chmod(tmp, stat.S_IMODE(st.st_mode))
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return given
