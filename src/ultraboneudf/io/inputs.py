"""Checks of a file given to read, before anything is read from it: that it is there, is a regular
file (a named pipe would wait for a writer forever, a device never ends), can be read, and that what
it holds fits in the memory there is."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from ..errors import InputError

_KINDS = {stat.S_ISFIFO: "a named pipe (FIFO)", stat.S_ISCHR: "a character device",
          stat.S_ISBLK: "a block device", stat.S_ISSOCK: "a socket"}


def check_input(path: str | os.PathLike, what: str = "file", folder: bool = False) -> Path:
    """``path`` as a :class:`Path` when it names a readable regular file (or, with ``folder``, a
    folder); else :class:`InputError` naming it: missing, a folder where a file is wanted, a named
    pipe, a device, a socket, or unreadable. ``what`` says what the file should be."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise InputError(f"{path}: no such {what}") from None
    except NotADirectoryError:
        raise InputError(f"{path}: no such {what} (a part of the path is a file)") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    except ValueError:  # an embedded NUL
        raise InputError(f"{path!r}: not a valid file name") from None
    for test, kind in _KINDS.items():
        if test(mode):
            raise InputError(f"{path}: is {kind}, not a regular {what}; give a file")
    if stat.S_ISDIR(mode):
        if not folder:
            raise InputError(f"{path}: is a folder, not a {what}")
        if not os.access(path, os.R_OK | os.X_OK):
            raise InputError(f"{path}: cannot read the folder (Permission denied)")
        return path
    if not os.access(path, os.R_OK):
        raise InputError(f"{path}: cannot read the file (Permission denied)")
    return path


def available_memory() -> int | None:
    """Bytes this process can still allocate: the least of the system's available memory, the
    control group's limit less its use, and the address-space limit (``ulimit -v``); ``None``
    where none of them can be read."""
    found = []
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    found.append(int(line.split()[1]) * 1024)
                    break
    except (OSError, ValueError):
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text())
            found.append(max(0, int(limit) - used))
    except (OSError, ValueError):
        pass
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            with open("/proc/self/statm", encoding="ascii") as fh:
                used = int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
            found.append(max(0, soft - used))
    except (ImportError, OSError, ValueError):
        pass
    return min(found) if found else None


def check_fits_memory(path: str | os.PathLike, needed: int, what: str) -> None:
    """Raise :class:`InputError` naming ``path`` when reading it needs ``needed`` bytes (``what``
    says of what) and fewer are available."""
    free = available_memory()
    if free is not None and needed > free:
        raise InputError(f"{path}: {what} need about {needed / 2**30:.1f} GiB of memory, more than the "
                         f"{free / 2**30:.1f} GiB available; thin the data first (e.g. every 10th point)")
