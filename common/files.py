"""Atomic writes, the one implementation for every writer of the project: the server's folder store (records), the
HTTP client (downloads, frames), scene and model folders (runtime.scene, model_export.export), the S3 store's
downloads and the training checkpoints. A reader sees the old file (folder) or the new one, never a half-written
one."""

from __future__ import annotations

import os
import secrets
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any


@contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "wb", fsync: bool = False, **open_kw: Any) -> Iterator[IO]:
    """A file opened (``mode``: "wb" or "w", ``open_kw`` passed to open) beside ``path`` as .NAME.RANDOM.part
    (created with the umask's permissions) and renamed onto ``path`` when the block completes (after an fsync of
    its data with ``fsync``), so readers see the old file or the new one, never a half-written one; removed when
    the block raises."""
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_file: mode must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.part")
    try:
        with open(tmp, mode.replace("w", "x"), **open_kw) as f:
            yield f
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_folder(out: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling of ``out`` to fill; when the block succeeds it is renamed to ``out`` (an existing
    ``out`` is moved aside first and removed afterwards), when it raises it is removed. Readers never see a
    half-written folder under ``out``."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    os.chmod(tmp, 0o755)   # mkdtemp makes it private; the result is an ordinary folder
    try:
        yield tmp
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
            os.replace(out, old / out.name)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


__all__ = ["atomic_file", "atomic_folder"]
