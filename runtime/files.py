"""Format-tagged JSON documents (model.json, scene.json): read_json_doc. The atomic writes are
xyzcyl.common.files (one implementation for the runtime, the server, the client and training)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any


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
