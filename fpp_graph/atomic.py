"""Atomic file writes: write to a temporary file in the same folder, fsync, then rename.

A reader (or a resumed run after ``kill -9``) therefore sees either the old file or the whole
new one, never a truncated file. A failed write (a full disk, a stop) removes its temporary file
and leaves any earlier file as it was. The new file gets the mode a plain ``open`` would give it
under the process's umask (a temporary file is created 0600).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from fpp_graph.errors import OutputError
from fpp_graph.outputs import os_error


def process_umask() -> int:
    """The process's umask, read without changing it where Linux tells it (``/proc``, kernel
    4.7+): setting it to read it back would race with other threads creating files."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "w", replace: bool = True, **kwargs) -> Iterator[IO]:
    """Open ``path`` for writing atomically; the file appears only when the block succeeds.

    ``mode`` is ``"w"`` (text) or ``"wb"`` (binary). On an exception inside the block the
    temporary file is removed and any previous file at ``path`` is left untouched. With
    ``replace=False`` an existing ``path`` (even one made meanwhile by another process) is never
    replaced: OutputError instead. OSErrors become OutputErrors naming ``path``.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open supports modes 'w' and 'wb', not {mode!r}")
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    except OSError as exc:
        raise os_error(exc, target) from exc
    try:
        os.fchmod(fd, 0o666 & ~process_umask())
        with os.fdopen(fd, mode, **kwargs) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        _publish(tmp_name, target, replace)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp_name)
        if isinstance(exc, OSError):
            raise os_error(exc, target) from exc
        raise


def _publish(tmp_name: str, target: Path, replace: bool) -> None:
    if replace:
        os.replace(tmp_name, target)
        return
    try:  # a hard link fails if the target exists: the check and the write are one step
        os.link(tmp_name, target)
    except FileExistsError:
        raise OutputError(f"{target} exists: pass --overwrite to replace it, or choose another path") from None
    except OSError:  # a file system without hard links (FAT, some network shares): check, then rename
        if target.exists():
            raise OutputError(f"{target} exists: pass --overwrite to replace it, or choose another path") from None
        os.replace(tmp_name, target)
        return
    os.unlink(tmp_name)


def atomic_write_text(path: str | os.PathLike[str], text: str, replace: bool = True) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_open(path, "w", replace=replace, encoding="utf-8") as handle:
        handle.write(text)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, replace: bool = True) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_open(path, "wb", replace=replace) as handle:
        handle.write(data)
