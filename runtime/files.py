"""Folder and file helpers shared by the model folder writer (model_export.export), scene folders (runtime.scene),
the server's folder store and the training checkpoints: atomic file and folder replacement and format-tagged
JSON documents. (The client keeps its own atomic file: it must not import the runtime.)"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .errors import FieldError


@contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "wb", fsync: bool = False, **open_kw: Any) -> Iterator[IO]:
    """A file opened (``mode``: "wb" or "w", ``open_kw`` passed to open) beside ``path`` as .NAME.RANDOM.part and
    renamed onto ``path`` when the block completes (after an fsync of its data with ``fsync``), so readers see the
    old file or the new one, never a half-written one; removed when the block raises."""
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


def read_json_doc(path: str | os.PathLike, fmt: str, error: type[FieldError], what: str) -> dict[str, Any]:
    """The JSON object in ``path`` whose "format" is ``fmt``; ``error`` (a FieldError whose field is ``what``, the
    file's role, with a message naming the file) when it is missing, not JSON or of another format."""
    p = Path(path)
    if not p.is_file():
        raise error(what, f"{str(p)!r} is missing (not a {what} folder)")
    try:
        doc = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise error(what, f"{str(p)!r} is not valid JSON ({e})") from None
    if not isinstance(doc, dict) or doc.get("format") != fmt:
        raise error(what, f"{str(p)!r} is not an {fmt} file")
    return doc
