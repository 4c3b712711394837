"""Files written once and read once, past the page cache (Linux's O_DIRECT): a drive's camera layer files while the
drive is reconstructed (runtime.cameralayers, runtime.drive).

Why: a reconstruction of 20 PandaSet keyframes writes ~4 GB of camera layers while it works and reads their shared
cells once at its end. Written through the page cache, every page of those files is a fresh page of memory the
kernel finds and fills, and on the 2-core machine measured (a VM, 2026-12-03) that costs far more than the copy:
`dd` of 4.2 GB buffered took 8.9 s of system time (0.46 GB/s; 0.19 s when the same file's pages were cached
already), with O_DIRECT 0.31 s of system time and 2.3 s of wall time, the disk's, while the cores do other work.
The same for reading a file not in the cache: 2.66 s of system time for 2 GB buffered, 0.26 s direct. In the drive's
reconstruction the buffered writes were 11 % of its CPU time (perf).

O_DIRECT moves whole aligned blocks between the disk and memory aligned to ALIGN. ``DirectWriter`` gathers a
file's bytes in one aligned buffer and writes its full blocks, the last block padded and the file cut back to its
size; ``DirectReader`` reads an aligned range around the bytes asked for into a caller's aligned buffer. Where the
file system refuses O_DIRECT (EINVAL: tmpfs on older kernels, some network file systems) or the platform has none,
both go through the page cache as any file does: the same bytes, only slower here.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

ALIGN = 4096        # O_DIRECT's alignment of memory, file offsets and lengths: a page, a multiple of every logical
                    # block size Linux's block devices use (512 or 4096)
_O_DIRECT = getattr(os, "O_DIRECT", 0)      # 0 where the platform has none (macOS): the page cache


def aligned_buffer(nbytes: int) -> np.ndarray:
    """[nbytes] uint8 whose first byte lies at an address that is a multiple of ALIGN (numpy aligns to 64 bytes)."""
    raw = np.empty(int(nbytes) + ALIGN, np.uint8)
    at = (-raw.ctypes.data) % ALIGN
    return raw[at:at + int(nbytes)]


def _refused(exc: OSError) -> bool:
    """An O_DIRECT open or transfer the file system refuses (it takes the page cache's way instead)."""
    return exc.errno in (errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP)


def _open(path: Path, flags: int) -> tuple[int, bool]:
    """(a descriptor of ``path`` opened with ``flags``, and O_DIRECT where the file system takes it: whether)."""
    if _O_DIRECT:
        try:
            return os.open(path, flags | _O_DIRECT, 0o644), True
        except OSError as exc:
            if not _refused(exc):
                raise
    return os.open(path, flags, 0o644), False


def _transfer(file: DirectWriter | DirectReader, move: Callable[[], int]) -> int:
    """move() (a write or read on ``file``'s descriptor: its bytes); where O_DIRECT's transfer is refused, the
    descriptor turned to the page cache's way (``file.direct`` False) and move() again."""
    try:
        return move()
    except OSError as exc:
        if not (file.direct and _refused(exc)):
            raise
    # POSIX only (Windows has none): reached only where O_DIRECT is
    import fcntl

    fcntl.fcntl(file._fd, fcntl.F_SETFL, fcntl.fcntl(file._fd, fcntl.F_GETFL) & ~_O_DIRECT)
    file.direct = False
    return move()


class DirectWriter:
    """A new file ``path`` written from the start, past the page cache: ``write`` bytes, or ``space`` then
    ``advance`` to fill the buffer in place (no copy of what a caller makes there); ``close`` writes the rest. One
    buffer of ``buffer_bytes`` (rounded up to ALIGN, two blocks at least) holds what is not written yet. A context
    manager: on an exception the file is closed as far as it was written (the caller removes it)."""

    def __init__(self, path: str | os.PathLike, buffer_bytes: int):
        self.path = Path(path)
        size = max(2 * ALIGN, -(-int(buffer_bytes) // ALIGN) * ALIGN)
        self._buf = aligned_buffer(size)
        self._fill = 0          # bytes in the buffer, not written yet
        self._size = 0          # the file's bytes so far (written and in the buffer)
        self._fd, self.direct = _open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)

    def __enter__(self) -> DirectWriter:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        if kind is None:
            self.close()
        elif self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    @property
    def size(self) -> int:
        """The file's bytes so far."""
        return self._size

    def space(self, nbytes: int) -> np.ndarray:
        """[nbytes] uint8 of the buffer where the next ``nbytes`` go (the full blocks before them written first);
        ``advance(nbytes)`` when they are there. ValueError when they cannot fit beside a partial block."""
        if self._fill + nbytes > len(self._buf):
            self._flush()
            if self._fill + nbytes > len(self._buf):
                raise ValueError(f"nbytes: {nbytes} do not fit the writer's buffer of {len(self._buf)} bytes "
                                 f"beside the {self._fill} of its last block")
        return self._buf[self._fill:self._fill + nbytes]

    def advance(self, nbytes: int) -> None:
        """The ``nbytes`` put in ``space`` are the file's next."""
        self._fill += nbytes
        self._size += nbytes

    def write(self, data: bytes | np.ndarray) -> None:
        """``data``'s bytes, next (through the buffer, a part at a time when longer than it)."""
        b = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else \
            np.ascontiguousarray(data).reshape(-1).view(np.uint8)
        at = 0
        while at < len(b):
            if self._fill == len(self._buf):
                self._flush()               # a partial block (< ALIGN) stays: room for ALIGN more at least
            n = min(len(b) - at, len(self._buf) - self._fill)
            self._buf[self._fill:self._fill + n] = b[at:at + n]
            self.advance(n)
            at += n

    def _flush(self, last: bool = False) -> None:
        """The buffer's full blocks written (``last``: the partial one too, padded) and the partial block moved to
        the buffer's start."""
        n = -(-self._fill // ALIGN) * ALIGN if last else self._fill // ALIGN * ALIGN
        view = memoryview(self._buf[:n])
        while len(view):
            view = view[_transfer(self, lambda: os.write(self._fd, view)):]
        rest = self._fill - n
        if rest > 0:
            self._buf[:rest] = self._buf[n:self._fill]
        self._fill = max(rest, 0)

    def close(self) -> None:
        """The rest written and the file cut back to its size (the last block's padding gone); closed."""
        if self._fd < 0:
            return
        try:
            self._flush(last=True)
            os.ftruncate(self._fd, self._size)
        finally:
            os.close(self._fd)
            self._fd = -1


def _pread_into(fd: int, view: memoryview, at: int) -> int:
    """Bytes of ``fd`` from offset ``at`` read into ``view``: their count (os.preadv; where the platform has none,
    macOS, os.pread and a copy)."""
    if hasattr(os, "preadv"):
        return os.preadv(fd, [view], at)
    got = os.pread(fd, len(view), at)
    view[:len(got)] = got
    return len(got)


class DirectReader:
    """A file's byte ranges read past the page cache into a caller's aligned buffer (``read``); where O_DIRECT is
    refused, through the cache. A context manager (closes the file)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._fd, self.direct = _open(self.path, os.O_RDONLY)
        self.file_size = os.fstat(self._fd).st_size

    def __enter__(self) -> DirectReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    @staticmethod
    def buffer_bytes(span: int) -> int:
        """The buffer ``read`` needs for ranges of up to ``span`` bytes (their aligned blocks)."""
        return (-(-int(span) // ALIGN) + 1) * ALIGN

    def read(self, start: int, stop: int, buf: np.ndarray) -> np.ndarray:
        """The file's bytes start..stop - 1 ([stop - start] uint8, a view of ``buf``: aligned_buffer of at least
        buffer_bytes(stop - start)); OSError (EIO) when the file is shorter."""
        lo = start // ALIGN * ALIGN
        hi = min(-(-stop // ALIGN) * ALIGN, -(-self.file_size // ALIGN) * ALIGN)
        if stop > self.file_size or hi - lo > len(buf):
            raise OSError(errno.EIO, f"bytes {start}..{stop} of {self.path.name!r} ({self.file_size} bytes) "
                                     f"into a buffer of {len(buf)}")
        view = memoryview(buf[:hi - lo])
        at = lo
        while len(view):
            got = _transfer(self, lambda: _pread_into(self._fd, view, at))
            if got == 0:                # the end of the file (its last block partial)
                break
            view, at = view[got:], at + got
        if at < stop:
            raise OSError(errno.EIO, f"{self.path.name!r} ended at byte {at}, before {stop}")
        return buf[start - lo:stop - lo]
