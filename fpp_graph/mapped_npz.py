"""Arrays of an uncompressed ``.npz`` (what ``np.savez`` writes) as read-only views of the file.

``np.load`` reads every member of an ``.npz`` through :mod:`zipfile`: the bytes are copied from
the page cache into a buffer, checksummed (CRC-32) and copied again into fresh arrays whose pages
the kernel must first clear. A decoded 1920x1200 frame is ~30 MB, and a run reads each keyframe
again for every loop it verifies (a 72-view FPP sequence: ~310 reads of 9 GB in total; ``perf``
put the CRC alone at 2.6 % of the run's cycles, the copies and the fresh pages on top). ``np.savez``
stores its members uncompressed, so each array lies in the file as an ``.npy`` record: this
module maps the file once and hands out views of it (pages come straight from the page cache,
and are shared by every process that reads the same frame).

The views are read-only. A file replaced or deleted while mapped keeps its old contents for
its views (POSIX); the mapping ends when the last view is released. A file *truncated in place*
while mapped would fault the process that reads a view past the new end (SIGBUS): the frame
store never writes in place (:func:`fpp_graph.atomic.atomic_open` writes a new file and renames
it over the old one), and :func:`mapped_npz` checks every member against the file's size when
it maps it. Each mapping holds a file descriptor until its last view is released, so a process
holds as many as it holds frames (the frame store keeps a few: a tracking process holds
about ten frame files mapped).
"""

from __future__ import annotations

import mmap
import os
import struct
import zipfile
from pathlib import Path

import numpy as np

# zip local file header: signature, version, flags, method, time, date, crc, sizes (2 x 4),
# name length, extra length (APPNOTE 4.3.7)
_LOCAL_HEADER = struct.Struct("<4s5H3I2H")
_LOCAL_SIGNATURE = b"PK\x03\x04"


def mapped_npz(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path``, by name (without ``.npy``), as read-only views of
    the mapped file; the same arrays ``np.load(path)`` gives.

    Raises
    ------
    OSError, zipfile.BadZipFile
        The file is missing or not a zip archive (a truncated write).
    ValueError
        A member is compressed, not an ``.npy`` record, holds Python objects, or reaches past
        the end of the file.
    """
    path = Path(path)
    with open(path, "rb") as handle:
        with zipfile.ZipFile(handle) as archive:
            members = archive.infolist()
        if not members:
            return {}
        mapped = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
    return {_name(info): _member_array(mapped, info, path) for info in members}


def _name(info: zipfile.ZipInfo) -> str:
    return info.filename[:-4] if info.filename.endswith(".npy") else info.filename


def _member_array(mapped: mmap.mmap, info: zipfile.ZipInfo, path: Path) -> np.ndarray:
    if info.compress_type != zipfile.ZIP_STORED:
        raise ValueError(f"{path}: member {info.filename} is compressed; only np.savez's stored members can be mapped")
    at = info.header_offset
    if at + _LOCAL_HEADER.size > len(mapped):
        raise ValueError(f"{path}: member {info.filename} starts past the end of the file")
    fields = _LOCAL_HEADER.unpack_from(mapped, at)
    if fields[0] != _LOCAL_SIGNATURE:
        raise ValueError(f"{path}: member {info.filename} has no local file header")
    start = at + _LOCAL_HEADER.size + fields[-2] + fields[-1]  # + name + extra (zip64 sizes live there)
    record = _Reader(mapped, start)
    version = np.lib.format.read_magic(record)
    if version not in _HEADER_READERS:  # 3.0 is for utf-8 field names, which frames never have
        raise ValueError(f"{path}: member {info.filename} is an npy {version[0]}.{version[1]} record; only 1.0 and 2.0 are mapped")
    shape, fortran_order, dtype = _HEADER_READERS[version](record)
    if dtype.hasobject:
        raise ValueError(f"{path}: member {info.filename} holds Python objects")
    end = record.position + dtype.itemsize * int(np.prod(shape, dtype=np.int64))
    if end > start + info.file_size or end > len(mapped):
        raise ValueError(f"{path}: member {info.filename} is cut short")
    return np.ndarray(shape, dtype=dtype, buffer=mapped, offset=record.position, order="F" if fortran_order else "C")


_HEADER_READERS = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}


class _Reader:
    """The ``read`` that ``np.lib.format``'s header functions need, over the map from ``position``."""

    def __init__(self, mapped: mmap.mmap, position: int) -> None:
        self.mapped, self.position = mapped, position

    def read(self, size: int) -> bytes:
        data = self.mapped[self.position : self.position + size]
        self.position += len(data)
        return data


__all__ = ["mapped_npz"]
