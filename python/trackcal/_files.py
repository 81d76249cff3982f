"""Writing output files that must never replace an existing one (a capture, a recording, residuals).

The data goes to a temporary file in the target's folder, is synced, and is then hard-linked to
the target: link() fails when the target exists, however late another file appeared there, where
a check followed by a rename would replace it. The C++ writers (core/capture.cc,
WriteFileAtomically) publish the same way.
"""

from __future__ import annotations

import errno
import os
import pathlib
import tempfile

# link() errors that mean the file system has no hard links (FAT, some network and FUSE mounts).
_NO_HARD_LINKS = {errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS, errno.EMLINK}


def write_new(path, data: bytes, exists_message: str = "exists; refusing to overwrite it") -> pathlib.Path:
    """Writes ``data`` to the new file ``path`` atomically. ValueError "<path>: <exists_message>"
    when path exists, and a ValueError saying so when the file system cannot hard-link (the file
    is then not written: no fallback could guarantee that nothing is replaced)."""
    path = pathlib.Path(path)
    if not path.parent.is_dir():  # else the error would name the temporary file
        raise ValueError(f"{path}: {path.parent} is not an existing folder")
    fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", dir=path.parent)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)  # as any new file (mkstemp makes it owner-only)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
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
