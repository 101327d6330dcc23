"""Results put in place as a unit: on any failure or signal, either the new result or the earlier
one is there, never a mix, and no temporary file is left.

A :class:`Commit` stages each file (or folder) of a result under a temporary name beside its target,
then puts them all in place:

1. a journal beside the first target lists the staged names, the targets and their backups;
2. every existing target gets a backup (a hard link for a file, a rename for a folder);
3. the staged names are renamed onto their targets, the targets to remove are moved away;
4. the journal is marked done (the moment the new result counts), the backups and the journal are
   removed.

SIGINT, SIGTERM and SIGHUP wait while steps 1–4 run (a few milliseconds) and take effect once the
result is complete; a signal while the files are staged removes them and leaves the earlier result.
A failure in steps 1–3 (a full disk) puts the backups back. A process killed outright (SIGKILL, the
out-of-memory killer) leaves its journal or its staged files: the next commit into the same folder,
and every output check before a run, first undoes the journal's half-done commit, or finishes one
marked done, and removes staged files of processes no longer running. The folders of a commit are
locked (``flock``) while it runs, so two processes writing the same output commit one after the
other. Data reach the disk in the operating system's own time (no ``fsync``): the guarantee is
against the process ending, not against a power cut.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import secrets
import shutil
import signal
import socket
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

STAGED = ".ubtmp"
"""Suffix of a staged file or folder (``.NAME.PID-HOST-TOKEN.ubtmp``) and of a backup (``….ubold``)."""
BACKUP = ".ubold"
JOURNAL = ".ultraboneudf-commit."
"""Prefix of a commit's journal: ``.ultraboneudf-commit.PID-HOST-TOKEN.json`` while the commit runs,
renamed to ``….done`` at the moment the new result counts."""

DEFERRED_SIGNALS = tuple(s for s in (getattr(signal, "SIGINT", None), getattr(signal, "SIGTERM", None),
                                     getattr(signal, "SIGHUP", None)) if s is not None)

_STEP_HOOK: Callable[[str], None] | None = None
"""Called with a description after every file operation of a commit (tests stop a process there)."""


class WriteError(OSError):
    """Writing an output failed after the work was done (a full disk, an I/O error); the earlier
    output is still in place and nothing of the new one is left. The message names the file."""


def _write_error(target: str | os.PathLike, exc: OSError) -> WriteError:
    return WriteError(exc.errno, f"{target}: cannot write ({exc.strerror or exc}); nothing written, the "
                                 f"earlier output kept")


def _step(what: str) -> None:
    if _STEP_HOOK is not None:
        _STEP_HOOK(what)


# ------------------------------------------------------------------------------------------------
# signals


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """While the block runs, SIGINT, SIGTERM and SIGHUP are held; when it ends they take effect as
    they would have (their handler runs, or the default action ends the process). Only the main
    thread can hold signals; elsewhere the block runs as is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = {}
    try:
        for sig in DEFERRED_SIGNALS:
            before = signal.getsignal(sig)
            signal.signal(sig, lambda signum, frame: held.append(signum))
            previous[sig] = signal.SIG_DFL if before is None else before
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(held):
            signal.raise_signal(sig)


# ------------------------------------------------------------------------------------------------
# names


_HOST = hashlib.sha1(socket.gethostname().encode()).hexdigest()[:6]
"""This machine, in the names of staged files: a folder shared between machines (a cluster's
storage) is cleaned only of the staged files of this machine's dead processes."""


def _token() -> str:
    return f"{os.getpid()}-{_HOST}-{secrets.token_hex(4)}"


def staged_name(target: Path, suffix: str = STAGED) -> Path:
    """A new name beside ``target`` for its staged content or its backup. Short whatever the
    target's length (a name the file system holds whenever it holds the target's)."""
    return target.with_name(f".{target.name[:24]}.{_token()}{suffix}")


def _owner_pid(name: str) -> int | None:
    """The id of the process of this machine whose staged, backup or journal name this is (``None``:
    another machine's, or not such a name)."""
    try:
        pid, host, _ = name.rsplit(".", 2)[-2].split("-")
        return int(pid) if host == _HOST else None
    except ValueError:
        return None


def _running(pid: int) -> bool:
    if pid == os.getpid() or os.name == "nt":  # (on Windows os.kill would end the process)
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _remove(path: Path) -> None:
    """Remove a file, a link or a folder tree; nothing if it is not there (or cannot be removed)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            path.unlink()


# ------------------------------------------------------------------------------------------------
# locks


@contextlib.contextmanager
def _locked(folders: list[Path]) -> Iterator[None]:
    """Exclusive ``flock`` on each folder, taken in a fixed order (no deadlock between commits)."""
    try:
        import fcntl
    except ImportError:  # no flock (Windows): commits into one folder are not serialised
        yield
        return
    fds = []
    try:
        for folder in sorted({str(f.resolve()) for f in folders}):
            fd = os.open(folder, os.O_RDONLY)
            fds.append(fd)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        for fd in reversed(fds):
            os.close(fd)  # closing releases the lock


# ------------------------------------------------------------------------------------------------
# the journal and recovery


@dataclass
class _Entry:
    target: Path                   # absolute
    staged: Path | None            # None: the target is removed
    backup: Path | None = None     # where the earlier target went (set in the commit)
    existed: bool = False
    placed: bool = False           # the staged content is at the target now
    shown: str = ""                # the target as the caller named it (for messages)

    def as_dict(self) -> dict:
        return {"target": str(self.target), "staged": None if self.staged is None else str(self.staged),
                "backup": None if self.backup is None else str(self.backup), "existed": self.existed}


def _write_journal(path: Path, entries: list[_Entry]) -> None:
    tmp = staged_name(path)
    try:
        with open(tmp, "x", encoding="utf-8") as fh:
            json.dump([e.as_dict() for e in entries], fh)
        os.replace(tmp, path)
    except BaseException:
        _remove(tmp)
        raise


def _undo(entries: list[_Entry]) -> None:
    """Put every backup back and remove what the commit placed; staged leftovers removed."""
    for e in reversed(entries):
        if e.backup is not None and os.path.lexists(e.backup):
            if e.backup.is_dir() and not e.backup.is_symlink():
                _remove(e.target)
                os.rename(e.backup, e.target)
            else:
                if e.target.is_dir() and not e.target.is_symlink():
                    _remove(e.target)
                os.replace(e.backup, e.target)
        elif not e.existed and e.placed:
            _remove(e.target)
        if e.staged is not None:
            _remove(e.staged)


def _finish(entries: list[_Entry]) -> None:
    for e in entries:
        if e.backup is not None:
            _remove(e.backup)
            _step(f"drop backup {e.target.name}")
        if e.staged is not None:
            _remove(e.staged)


def recover(folder: str | os.PathLike) -> None:
    """Finish or undo the commits into ``folder`` that a killed process left half-done (see the
    module doc), and remove staged files and backups of processes no longer running."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    try:
        names = os.listdir(folder)
    except OSError:
        return
    journals = [folder / n for n in names if n.startswith(JOURNAL) and n.endswith((".json", ".done"))]
    for journal in journals:
        pid = _owner_pid(journal.name)
        if pid is None or _running(pid):
            continue
        try:
            entries = [_Entry(Path(e["target"]), None if e["staged"] is None else Path(e["staged"]),
                              None if e["backup"] is None else Path(e["backup"]), bool(e["existed"]))
                       for e in json.loads(journal.read_text(encoding="utf-8"))]
        except (OSError, ValueError, KeyError, TypeError):
            continue  # not a journal of ours: left alone
        folders = [journal.parent, *(e.target.parent for e in entries)]
        with _locked([f for f in folders if f.is_dir()]), signals_deferred():
            if not journal.exists():
                continue  # another process recovered it meanwhile
            if journal.suffix == ".done":
                _finish(entries)
            else:
                for e in entries:  # what stands at the target is ours when its staged name is gone
                    e.placed = e.staged is not None and not os.path.lexists(e.staged) \
                        and os.path.lexists(e.target)
                _undo(entries)
            _remove(journal)
    for name in names:
        if name.startswith(".") and name.endswith((STAGED, BACKUP)):
            pid = _owner_pid(name)
            if pid is not None and not _running(pid):
                _remove(folder / name)


# ------------------------------------------------------------------------------------------------
# the commit


class Commit:
    """The files and folders of one result, staged and then put in place together.

    >>> with Commit() as c:                                          # doctest: +SKIP
    ...     c.write(Path("bone.ply"), mesh_bytes)
    ...     c.write(Path("bone.ply.json"), sidecar_bytes)
    ...     c.remove(Path("bone.ply.ckpt"))
    ...     c.commit()

    Leaving the ``with`` block without :meth:`commit` (an exception, a signal) removes whatever was
    staged. ``verify`` (given to :meth:`commit`) runs with the folders locked, just before anything
    is replaced: it raises to refuse (e.g. a file that appeared at a target during the run).
    """

    def __init__(self) -> None:
        self._entries: list[_Entry] = []
        self._done = False

    def __enter__(self) -> "Commit":
        return self

    def __exit__(self, *exc) -> None:
        if not self._done:
            self.discard()

    def _add(self, given: str | os.PathLike, staged: bool) -> _Entry:
        target = Path(os.path.abspath(given))
        if any(e.target == target for e in self._entries):
            raise ValueError(f"{target}: given twice in one commit")
        entry = _Entry(target, staged_name(target) if staged else None, shown=str(given))
        self._entries.append(entry)
        return entry

    def write(self, target: str | os.PathLike, data: bytes) -> None:
        """Stage ``data`` as the new content of the file ``target`` (with the permissions a plain
        ``open`` gives a new file)."""
        entry = self._add(target, staged=True)  # the staged name is known before the file exists
        try:
            entry.target.parent.mkdir(parents=True, exist_ok=True)
            with open(entry.staged, "xb") as fh:
                _step(f"create {entry.staged.name}")
                fh.write(data)
        except OSError as exc:
            raise _write_error(entry.shown, exc) from None
        _step(f"write {entry.staged.name}")

    def file(self, target: str | os.PathLike) -> Path:
        """A new empty staged file for the content of the file ``target``, for a writer that needs a
        path (SQLite); returns its name."""
        entry = self._add(target, staged=True)
        try:
            entry.target.parent.mkdir(parents=True, exist_ok=True)
            with open(entry.staged, "xb"):
                pass
        except OSError as exc:
            raise _write_error(entry.shown, exc) from None
        _step(f"create {entry.staged.name}")
        return entry.staged

    def folder(self, target: str | os.PathLike) -> Path:
        """A new empty folder to fill with the content of the folder ``target``; returns it."""
        entry = self._add(target, staged=True)
        try:
            entry.target.parent.mkdir(parents=True, exist_ok=True)
            entry.staged.mkdir()
        except OSError as exc:
            raise _write_error(entry.shown, exc) from None
        _step(f"create {entry.staged.name}")
        return entry.staged

    def remove(self, target: str | os.PathLike) -> None:
        """Remove the file or folder ``target`` as part of the commit (when it exists then)."""
        self._add(target, staged=False)

    def discard(self) -> None:
        """Remove everything staged (signals held meanwhile, so the clean-up itself completes)."""
        with signals_deferred():
            for e in self._entries:
                if e.staged is not None:
                    _remove(e.staged)
            self._entries = []
            self._done = True

    def commit(self, verify: Callable[[], None] | None = None) -> None:
        """Put every staged file and folder in place and remove the targets to remove, as a unit.
        Raises :class:`WriteError` (everything as before) when the file system refuses."""
        entries = [e for e in self._entries if e.staged is not None or os.path.lexists(e.target)]
        single = verify is None and len(entries) == 1 and entries[0].staged is not None \
            and not entries[0].staged.is_dir()
        folders = [] if single else sorted({e.target.parent for e in entries}, key=str)
        try:
            for folder in folders:
                recover(folder)
            with _locked(folders), signals_deferred():
                if verify is not None:
                    verify()
                for e in entries:
                    e.existed = os.path.lexists(e.target)
                if single:  # one file, nothing to check: one rename is atomic as it is
                    os.replace(entries[0].staged, entries[0].target)
                    _step(f"replace {entries[0].target.name}")
                elif entries:
                    self._commit_many(entries)
        except WriteError:
            self.discard()
            raise
        except OSError as exc:
            self.discard()
            raise _write_error(entries[0].shown if entries else "output", exc) from None
        except BaseException:
            self.discard()
            raise
        self._done = True

    def _commit_many(self, entries: list[_Entry]) -> None:
        journal = entries[0].target.parent / f"{JOURNAL}{_token()}.json"
        done = journal.with_suffix(".done")
        for e in entries:
            if e.existed:
                e.backup = staged_name(e.target, BACKUP)
        try:
            _write_journal(journal, entries)
            _step("journal")
            for e in entries:
                if e.existed:
                    if e.target.is_dir() and not e.target.is_symlink():
                        os.rename(e.target, e.backup)
                    else:
                        try:
                            os.link(e.target, e.backup, follow_symlinks=False)
                        except OSError:  # no hard links here: the rename leaves a moment without it
                            os.rename(e.target, e.backup)
                    _step(f"backup {e.target.name}")
            for e in entries:
                if e.staged is None:
                    if os.path.lexists(e.target):
                        _remove(e.target)  # its backup holds it until the journal says done
                    _step(f"remove {e.target.name}")
                    continue
                if e.staged.is_dir():
                    if os.path.lexists(e.target):
                        _remove(e.target)  # a file or link, its backup a hard link of it
                    os.rename(e.staged, e.target)
                else:
                    os.replace(e.staged, e.target)
                e.placed = True
                _step(f"replace {e.target.name}")
            os.rename(journal, done)  # the moment the new result counts
        except BaseException:
            _undo(entries)
            _remove(journal)
            raise
        _step("journal done")
        _finish(entries)
        _remove(done)
        _step("journal removed")
