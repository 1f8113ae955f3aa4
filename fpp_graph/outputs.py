"""Where commands write: nothing of the user's is replaced unasked, nothing written into an input,
no two writers in one folder, and every operating-system error one line that says what to do.

Every command that writes follows the same rules:

- :func:`refuse_input_overlap`: an output is never an input, inside an input folder, or a folder
  holding an input (``--overwrite`` would delete it);
- :func:`claim_output_folder`: an output folder is held under an advisory lock
  (:class:`FolderLock`) while the command writes it, and the files the command writes must not
  exist yet unless ``--overwrite`` was given;
- :func:`refuse_existing_file`: the same for a single output file (the write itself is atomic,
  :mod:`fpp_graph.atomic`);
- :func:`os_error`: an :class:`OSError` on a path becomes an :class:`~fpp_graph.errors.FppError`
  naming the path and what to do (the CLI shows it as one line; ``fpp-slam`` turns any OSError
  that reaches it the same way).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from collections.abc import Iterable, Iterator
from pathlib import Path

from fpp_graph.errors import FppError, InputDataError, OutputError

#: The lock file of a folder being written; hidden, and left in place (it is empty of meaning once
#: no process holds its lock: the kernel releases an ``flock`` when its holder ends, even on kill -9).
LOCK_NAME = ".fpp-slam.lock"

#: What to do about an OSError, by errno.
_ADVICE = {
    errno.EACCES: "check its permissions (and those of the folders above it)",
    errno.EPERM: "check its permissions (and those of the folders above it)",
    errno.EROFS: "it is on a read-only file system: choose a path on a writable one",
    errno.ENOSPC: "the disk is full: free some space, or choose a path on another disk",
    errno.EDQUOT: "the disk quota is exceeded: free some space, or choose a path on another disk",
    errno.ENOTDIR: "a part of the path is a file, not a folder: choose another path",
    errno.EISDIR: "it is a folder: give a file's path",
    errno.ENOENT: "it does not exist: check the path",
    errno.EEXIST: "it exists already: choose another path",
    errno.ENAMETOOLONG: "the name is too long: choose a shorter path",
    errno.ENOTEMPTY: "the folder is not empty: choose another path",
    errno.EIO: "the device reported an input/output error: check the disk",
}


def os_error(exc: OSError, path: str | os.PathLike[str] | None = None, reading: bool | None = False) -> FppError:
    """``exc`` as an FppError: ``cannot read|write|use PATH: <reason>; <what to do>``.

    The path is the one the OSError names, else ``path``. Reading errors are
    :class:`~fpp_graph.errors.InputDataError`, writing errors :class:`~fpp_graph.errors.OutputError`
    (``reading=None``: not known which, a plain FppError).
    """
    where = exc.filename if exc.filename is not None else (path if path is not None else "a file")
    reason = exc.strerror or str(exc) or type(exc).__name__
    advice = _ADVICE.get(exc.errno, "check the path")
    kind, verb = {True: (InputDataError, "read"), False: (OutputError, "write"), None: (FppError, "use")}[reading]
    return kind(f"cannot {verb} {where}: {reason}; {advice}")


@contextlib.contextmanager
def translated_os_errors(path: str | os.PathLike[str] | None = None, reading: bool | None = False) -> Iterator[None]:
    """Run the block with every OSError raised as :func:`os_error` (FppErrors pass unchanged)."""
    try:
        yield
    except OSError as exc:
        raise os_error(exc, path, reading) from exc


def _resolved(path: Path) -> Path:
    return Path(os.path.realpath(path))


def refuse_input_overlap(out: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str] | None], option: str = "--out") -> None:
    """Raise OutputError when ``out`` is one of ``inputs``, lies inside an input folder, or is a
    folder that holds an input (symbolic links resolved). ``None`` inputs are ignored."""
    target = _resolved(Path(out))
    for given in inputs:
        if given is None:
            continue
        source = _resolved(Path(given))
        if target == source:
            raise OutputError(f"{option} {out} is the input {given}: the command never writes into its own input; choose another {option}")
        if target.is_relative_to(source) and source.is_dir():
            raise OutputError(f"{option} {out} is inside the input folder {given}: writing there would change the input; choose a folder outside it")
        if source.is_relative_to(target):
            raise OutputError(f"{option} {out} holds the input {given}: replacing it could delete the input; choose another {option}")


def refuse_existing_file(path: str | os.PathLike[str], overwrite: bool, option: str = "--out") -> None:
    """Raise OutputError when ``path`` is a folder, or exists and ``overwrite`` is false."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{option} {path} is a folder: give the path of a file to write")
    if path.exists() and not overwrite:
        raise OutputError(f"{option} {path} exists: pass --overwrite to replace it, or choose another {option}")
    if path.parent.exists() and not path.parent.is_dir():
        raise OutputError(f"{option} {path}: {path.parent} is a file, not a folder; choose another {option}")


class FolderLock:
    """An advisory, exclusive lock on a folder (``flock`` on its :data:`LOCK_NAME` file).

    A second process asking for the lock is refused at once with OutputError naming the holder's
    PID; the lock ends with its holder, whatever way it ends. Use as a context manager.
    """

    def __init__(self, folder: str | os.PathLike[str], option: str = "--out") -> None:
        self.folder = Path(folder)
        self.option = option
        self._fd: int | None = None

    def acquire(self) -> None:
        lock_path = self.folder / LOCK_NAME
        with translated_os_errors(lock_path):
            fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            raise OutputError(
                f"{self.option} {self.folder} is being written by another fpp-slam process (PID {holder}); "
                f"wait for it to end, or choose another {self.option}"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, 0)
            os.close(self._fd)  # closing the last descriptor releases the flock
            self._fd = None

    def __enter__(self) -> FolderLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def make_folder(folder: str | os.PathLike[str], option: str = "--out") -> Path:
    """Create ``folder`` (and its parents); OutputError when it is a file or cannot be made."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{option} {folder} is a file, not a folder: choose another {option}")
    with translated_os_errors(folder):
        folder.mkdir(parents=True, exist_ok=True)
    return folder


@contextlib.contextmanager
def claim_output_folder(
    folder: str | os.PathLike[str], writes: Iterable[str], overwrite: bool = False,
    inputs: Iterable[str | os.PathLike[str] | None] = (), option: str = "--out",
) -> Iterator[Path]:
    """Hold ``folder`` for a command that writes the files named ``writes`` into it.

    Refused (OutputError, nothing created or changed) when the folder overlaps an input, is a
    file, is being written by another process, or already holds one of ``writes`` and
    ``overwrite`` is false. Other files of the user's in the folder are left alone. The lock is
    held until the block ends; OSErrors inside the block become FppErrors naming the folder.
    """
    folder = Path(folder)
    refuse_input_overlap(folder, inputs, option)
    make_folder(folder, option)
    with FolderLock(folder, option):
        existing = sorted(name for name in writes if (folder / name).exists())
        if existing and not overwrite:
            shown = ", ".join(existing[:4]) + (", ..." if len(existing) > 4 else "")
            raise OutputError(f"{option} {folder} already holds {shown}: pass --overwrite to replace them, or choose another {option}")
        with translated_os_errors(folder):
            yield folder
