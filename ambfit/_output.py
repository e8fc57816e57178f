"""Output files that are never left half-written and never replace what they should write into.

Every file ambfit writes (the command line's JSON, CSV, NetCDF and PNG, the reports, the rig's truth) goes
through :func:`write_with` (or :func:`write_bytes`, :func:`write_text`, :func:`write_json` on top of it):

- a regular file (or a new one) is written to a temporary file in the destination's folder, flushed to disk and
  renamed over the destination only when complete: a full disk, a crash or Ctrl-C leaves the old file as it was
  and no temporary file behind.  A process killed outright (SIGKILL, a power cut) cannot clean up: its
  temporary file (``.NAME.PID.XXXX.tmp``) is removed by the next write of the same file, once no process of
  that number runs.  The new file keeps the old one's permissions (and owner, where allowed).
- a symbolic link is followed: the file it points to is replaced as above and the link stays a link.
- a character device, FIFO or other non-regular file (``/dev/null``, a named pipe) is written into directly;
  it is never replaced by a regular file.

:func:`unwritable` says, before any work, why an output could not be written.  A write that fails raises
:class:`OutputError` (an :class:`OSError`) whose message names the file and the reason.  Writers in native
libraries that may not survive a full disk (HDF5) should serialise to memory and use :func:`write_bytes`.

Example
-------
>>> import tempfile, os
>>> folder = tempfile.mkdtemp()
>>> path = write_text(os.path.join(folder, "a.txt"), "hello\\n")
>>> open(path).read(), os.listdir(folder)
('hello\\n', ['a.txt'])
"""

from __future__ import annotations

import errno
import glob
import json
import os
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


class OutputError(OSError):
    """An output file could not be written; the message (``strerror``) names the file and the reason."""

    def __str__(self) -> str:
        return str(self.strerror)


def destination(path: str | os.PathLike) -> Path:
    """Where a write to ``path`` lands: the file at the end of its symbolic links (``path`` itself otherwise)."""
    return Path(os.path.realpath(path))


def unwritable(path: str | os.PathLike, *, folder: bool = False, parents: bool = False) -> str | None:
    """Why ``path`` cannot be written (a sentence naming it), or ``None`` when it can.

    ``folder``: ``path`` is a folder to create or write into.  ``parents``: missing folders on the way will be
    created (as a report's folder is), so only the nearest existing one must be a writable folder.
    """
    path = Path(path)
    try:
        return _unwritable(path, folder, parents)
    except OSError as exc:              # a name the file system refuses (too long, a bad byte), a vanished folder
        return f"{path}: cannot be written ({exc.strerror or exc})"


TEMPORARY_SUFFIX = 24
"""How much longer than its destination's a temporary file's name is (``.NAME.PID.XXXXXXXX.tmp``)."""


def _unwritable(path: Path, folder: bool, parents: bool) -> str | None:
    dest = destination(path)
    if dest.is_symlink():
        return f"{path}: a loop of symbolic links"
    try:
        st = dest.stat()
    except (FileNotFoundError, NotADirectoryError):   # (a file where a folder should be: named below)
        st = None
    except OSError as exc:
        return f"{path}: cannot be written ({exc.strerror})"
    if st is not None:
        if folder:
            if not stat.S_ISDIR(st.st_mode):
                return f"{path}: exists and is not a folder"
            return None if os.access(dest, os.W_OK) else f"{path}: the folder is not writable"
        if stat.S_ISDIR(st.st_mode):
            return f"{path}: is a directory; give a file name"
        if stat.S_ISSOCK(st.st_mode):
            return f"{path}: is a socket, not a file"
        if not os.access(dest, os.W_OK):
            return f"{path}: exists and is read-only"
        if not stat.S_ISREG(st.st_mode):
            return None                        # a device or FIFO: written into directly
    parent = dest if folder else dest.parent
    probe = parent
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        return f"{path}: {probe} is a file, not a folder"
    if probe != parent and not (folder or parents):
        return f"{path}: the folder {parent} does not exist"
    if not os.access(probe, os.W_OK):
        return f"{path}: the folder {probe} is not writable"
    if not folder and (st is None or stat.S_ISREG(st.st_mode)):
        try:
            name_max = os.pathconf(probe, "PC_NAME_MAX")
        except (OSError, ValueError, AttributeError):
            name_max = 255
        if (n := len(os.fsencode(dest.name))) + TEMPORARY_SUFFIX > name_max:
            return (f"{path}: the file name is {n} bytes long; this file system allows {name_max - TEMPORARY_SUFFIX} "
                    "for an output (it is first written under a longer temporary name beside it)")
    return None


def write_with(path: str | os.PathLike, write: Callable[[BinaryIO], object]) -> Path:
    """Write the file ``path`` by calling ``write(f)`` with a binary file open for writing (see the module).

    Returns the path written (the link's target for a symbolic link).  Raises :class:`OutputError` when the file
    cannot be written; the destination is then as it was and no temporary file is left.  Anything else ``write``
    raises passes through, after the same clean-up.
    """
    path = Path(path)
    dest = destination(path)
    try:
        st = dest.stat()
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise _error(path, exc) from None
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise OutputError(errno.EISDIR, f"{path}: is a directory; give a file name")
    if st is not None and not stat.S_ISREG(st.st_mode):
        try:                                   # a device or FIFO: into it, never over it
            with open(dest, "wb") as f:
                write(f)
        except OSError as exc:
            raise _error(path, exc) from None
        return dest
    _remove_abandoned(dest)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=dest.parent, prefix=f".{dest.name}.{os.getpid()}.", suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        _copy_permissions(st, tmp)
        os.replace(tmp, dest)
        tmp = None
    except OSError as exc:
        raise _error(path, exc) from None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass
    return dest


def _remove_abandoned(dest: Path) -> None:
    """Remove the temporary files of earlier writes of ``dest`` whose process no longer runs."""
    try:
        left = list(dest.parent.glob(f".{glob.escape(dest.name)}.*.tmp"))
    except OSError:
        return
    for tmp in left:
        pid = tmp.name[len(dest.name) + 2:].split(".", 1)[0]
        if not pid.isdigit() or int(pid) == os.getpid() or _running(int(pid)):
            continue
        try:
            tmp.unlink()
        except OSError:
            pass


def _running(pid: int) -> bool:
    """Whether a process of number ``pid`` runs (always taken to on Windows, where signal 0 is Ctrl-C)."""
    if os.name == "nt":
        return True
    try:
        os.kill(pid, 0)
    except PermissionError:                 # another user's process
        return True
    except (OSError, OverflowError):        # none of that number
        return False
    return True


FORMULA_START = ("=", "+", "-", "@", "\t", "\r")
"""What makes a spreadsheet read a cell as a formula (OWASP "CSV injection")."""


def formula_safe(frame):
    """``frame`` (a pandas DataFrame) with every text cell a spreadsheet would run as a formula (``=cmd|...``,
    ``@SUM(...)``) quoted by a leading apostrophe; numbers, negative ones too, are left as they are."""
    import pandas as pd

    out = frame.copy()
    for c in out.columns:
        if not (out[c].dtype == object or pd.api.types.is_string_dtype(out[c].dtype)):
            continue
        out[c] = [f"'{v}" if isinstance(v, str) and v.startswith(FORMULA_START) and not _is_number(v) else v
                  for v in out[c]]
    return out


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def write_bytes(path: str | os.PathLike, data: bytes | memoryview) -> Path:
    """Write ``data`` to ``path`` (see :func:`write_with`)."""
    return write_with(path, lambda f: f.write(data))


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` as UTF-8 to ``path``, line ends as given (see :func:`write_with`)."""
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, record, **dump) -> Path:
    """Write ``record`` as indented JSON to ``path`` (see :func:`write_with`); ``dump``: more ``json.dumps``
    arguments (e.g. ``default=float``)."""
    return write_text(path, json.dumps(record, indent=2, **dump) + "\n")


def _copy_permissions(old: os.stat_result | None, tmp: str) -> None:
    """The new file gets the replaced file's mode and owner, or the usual mode of a new file (``mkstemp`` makes
    0600)."""
    if old is None:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        return
    os.chmod(tmp, stat.S_IMODE(old.st_mode))
    if (old.st_uid, old.st_gid) != (os.getuid(), os.getgid()):
        try:
            os.chown(tmp, old.st_uid, old.st_gid)
        except OSError:                        # only root may give a file away; the content matters more
            pass


def _error(path: Path, exc: OSError) -> OutputError:
    reason = exc.strerror or str(exc)
    return OutputError(exc.errno, f"{path}: could not be written ({reason}); any file that was there is unchanged")
