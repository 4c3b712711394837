"""A model folder (what `xyzcyl export-model` writes, what the runtime and the server load): its model.json
(``read_model_info`` -> ``ModelInfo``; ``ModelError`` naming the key or file at fault), its files checked against
model.json's sha256 (``read_model_file``, ``verify_model``), and the folder used when none is given
(``default_model_dir``).

Light on purpose: the standard library only (the lifting parameters are imported when asked for), so reading the
model's name and version (`xyzcyl --version`) imports neither numpy nor numba nor onnxruntime. runtime.inference
re-exports all of it."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .errors import FieldError
from .files import read_json_doc

if TYPE_CHECKING:
    from .lifting import LiftingParams

MODEL_FORMAT = "xyzcyl-model"


class ModelError(FieldError):
    """The model folder is missing, incomplete or altered: ``field`` the model.json key at fault ("name",
    "files", "graphs.encode.file"; ``where`` "model"), or "model" (the folder or a file of it as a whole)."""


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@dataclass(frozen=True)
class ModelInfo:
    """model.json of a model folder, parsed."""

    path: Path
    meta: dict[str, Any]

    @property
    def name(self) -> str:
        return str(self.meta["name"])

    @property
    def version(self) -> str:
        return str(self.meta["version"])

    @property
    def config(self) -> dict[str, Any]:
        return self.meta["config"]

    @property
    def input_size(self) -> tuple[int, int]:
        """(height, width) of the images the encode graph takes."""
        return int(self.meta["input"]["height"]), int(self.meta["input"]["width"])

    @property
    def depth_size(self) -> tuple[int, int]:
        d = self.meta["input"]["depth"]
        return int(d["height"]), int(d["width"])

    @property
    def lifting(self) -> LiftingParams:
        from .lifting import LiftingParams

        return LiftingParams.from_config_dict(self.config)

    @property
    def max_voxels(self) -> int:
        return int(self.meta["selection"]["max_voxels"])

    def graph_inputs(self, graph: str) -> list[str]:
        return [i["name"] for i in self.meta["graphs"][graph]["inputs"]]


def read_model_info(model_dir: str | os.PathLike) -> ModelInfo:
    """Parse ``model_dir/model.json`` (ModelError naming the file when absent or invalid)."""
    d = Path(model_dir)
    if not d.is_dir():
        raise ModelError("model", f"{str(d)!r} is not a folder")
    p = d / "model.json"
    meta = read_json_doc(p, MODEL_FORMAT, ModelError, "model")
    for key in ("name", "version", "config", "input", "graphs", "files", "selection"):
        if key not in meta:
            raise ModelError(key, f"is missing from {str(p)!r}", "model")
    return ModelInfo(d, meta)


def read_model_file(info: ModelInfo, name: str, verify: bool = True) -> bytes:
    """The bytes of a file of the model folder, checked against model.json's sha256 (ModelError naming it)."""
    entry = info.meta["files"].get(name)
    if entry is None:
        raise ModelError("files", f"{name!r} is not listed in {info.path / 'model.json'}", "model")
    p = info.path / name
    if not p.is_file():
        raise ModelError("model", f"file {name!r} is missing from {str(info.path)!r}")
    data = p.read_bytes()
    if verify and _sha256(data) != entry["sha256"]:
        raise ModelError("model", f"file {name!r} in {str(info.path)!r} is altered: sha256 {_sha256(data)[:16]}… "
                                  f"differs from model.json's {str(entry['sha256'])[:16]}…")
    return data


def verify_model(model_dir: str | os.PathLike) -> ModelInfo:
    """Check every file model.json lists (presence and sha256); returns the parsed model.json."""
    info = read_model_info(model_dir)
    for name in info.meta["files"]:
        read_model_file(info, name)
    return info


def default_model_dir() -> Path:
    """$XYZCYL_MODEL, else models/xyzcyl-cpu-v1 in the working folder, else in the source checkout."""
    env = os.environ.get("XYZCYL_MODEL")
    if env:
        return Path(env)
    local = Path("models") / "xyzcyl-cpu-v1"
    if local.is_dir():
        return local
    return Path(__file__).resolve().parents[1] / "models" / "xyzcyl-cpu-v1"


__all__ = ["MODEL_FORMAT", "ModelError", "ModelInfo", "default_model_dir", "read_model_file", "read_model_info",
           "verify_model"]
