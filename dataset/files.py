"""Files as a dataset handles them: read only when regular and bounded in size, written
atomically (temporary name, fsync, rename), checksummed."""

from __future__ import annotations

import errno
import hashlib
import os
import stat
from pathlib import Path

from dataset.records import DatasetError


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def read_regular_file(path: Path, limit: int, what: str) -> bytes:
    """The bytes of ``path``, which must be a regular file (not a symbolic link) of at most
    ``limit`` bytes. A named pipe would block a reader forever and /dev/zero never ends, so
    the kind and size are checked on the open file before a byte is read. OSError where the
    file cannot be opened; DatasetError where it is not one to read."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise DatasetError(f"{what} {path} is a symbolic link: a dataset holds its own files") from err
        raise
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise DatasetError(f"{what} {path} is not a regular file")
        if info.st_size > limit:
            raise DatasetError(f"{what} {path} is {info.st_size} bytes, over the limit of {limit}")
        chunks, total = [], 0
        while chunk := os.read(fd, min(1 << 20, limit + 1 - total)):
            chunks.append(chunk)
            total += len(chunk)
            if total > limit:
                raise DatasetError(f"{what} {path} grew past the limit of {limit} bytes while read")
        return b"".join(chunks)
    finally:
        os.close(fd)


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a crash leaves either the old file or the new one."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
