"""Folder and file helpers shared by the model folder writer (model_export.export) and scene folders
(runtime.scene): atomic folder replacement and format-tagged JSON documents."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


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


def read_json_doc(path: str | os.PathLike, fmt: str, error: type[Exception], what: str) -> dict[str, Any]:
    """The JSON object in ``path`` whose "format" is ``fmt``; ``error`` (message starting with ``what``, naming
    the file) when it is missing, not JSON or of another format."""
    p = Path(path)
    if not p.is_file():
        raise error(f"{what}: {str(p)!r} is missing (not a {what} folder)")
    try:
        doc = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise error(f"{what}: {str(p)!r} is not valid JSON ({e})") from None
    if not isinstance(doc, dict) or doc.get("format") != fmt:
        raise error(f"{what}: {str(p)!r} is not an {fmt} file")
    return doc
