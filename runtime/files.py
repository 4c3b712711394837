"""Format-tagged JSON documents (model.json, scene.json): read_json_doc. The atomic writes are
xyzcyl.common.files (one implementation for the runtime, the server, the client and training)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from xyzcyl.common.errors import FieldError


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
