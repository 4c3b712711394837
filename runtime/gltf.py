"""glTF 2.0 with Khronos' KHR_gaussian_splatting (github.com/KhronosGroup/glTF, extensions/2.0/Khronos/
KHR_gaussian_splatting): Gaussians as point primitives, one mesh per node, written as .glb (binary) or .gltf (the
JSON with its buffer inline as a base64 data URI: one self-contained file, a third larger).

Each node's primitive (mode POINTS) has, per Gaussian, all float32 but COLOR_0:

    POSITION                                   VEC3   the mean, metres (accessor min/max as glTF requires)
    KHR_gaussian_splatting:ROTATION            VEC4   the unit quaternion, glTF's order xyzw
    KHR_gaussian_splatting:SCALE               VEC3   the standard deviations exp(log_scales), metres
    KHR_gaussian_splatting:OPACITY             SCALAR sigmoid(opacity_logits)
    KHR_gaussian_splatting:SH_DEGREE_0_COEF_0  VEC3   the DC coefficients (colour = 0.2820948 * dc + 0.5)
    KHR_gaussian_splatting:SH_DEGREE_l_COEF_n  VEC3   degree l >= 1, n = 0..2l from order m = -l up: sh[:, l^2 + n]
    COLOR_0                                    VEC4   unsigned byte normalised: the fallback for viewers without
                                                      the extension (linear RGB of the DC colour, opacity)

with the extension's object {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"} (the Gaussians' colours
are the 8-bit camera images' values: display-referred sRGB; the SH basis and its signs are the renderer's,
runtime/render/sh.py, which are the extension's). The extension is used, not required: a viewer without it draws
the points. No material (the extension ignores one). Floats throughout, so a round trip loses only float32
rounding of the activated values.

Frames: a node's Gaussians are in that node's frame and its ``matrix`` (column-major, as glTF) places it in its
parent's; runtime.exports gives the Gaussians in glTF's frame (+Y up, +Z forward, +X left: docs/conventions.md
"Exchange formats") and a drive's actors as nodes."""

from __future__ import annotations

import base64
import json
import os
import struct
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import FieldError
from .render import Gaussians
from .render.gaussians import SH_C0, sigmoid

EXTENSION = "KHR_gaussian_splatting"
COLOR_SPACE = "srgb_rec709_display"
_FLOAT, _UBYTE = 5126, 5121                 # accessor componentType
_ARRAY_BUFFER = 34962                       # bufferView target of vertex attributes
_POINTS = 0
_GLB_MAGIC, _JSON, _BIN = 0x46546C67, 0x4E4F534A, 0x004E4942


class GltfError(FieldError):
    """A document glTF cannot hold (``field`` the node or array at fault)."""


@dataclass(frozen=True)
class SplatNode:
    """One node of the file: ``name`` (unique), its Gaussians in its own frame (metres), ``matrix`` [4, 4] node ->
    parent frame (rigid; None: identity, no matrix written) and ``extras`` (JSON values, the node's ``extras``)."""

    name: str
    gaussians: Gaussians
    matrix: np.ndarray | None = None
    extras: Mapping[str, Any] = field(default_factory=dict)


def attribute_name(degree: int, n: int) -> str:
    """The extension's semantic of SH coefficient ``n`` (0..2 degree) of ``degree``."""
    return f"{EXTENSION}:SH_DEGREE_{degree}_COEF_{n}"


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear (IEC 61966-2-1), in their dtype: COLOR_0 is linear by glTF's rule."""
    c = np.asarray(c)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(c.dtype)


def _columns(g: Gaussians) -> list[tuple[str, np.ndarray, bool]]:
    """(semantic, [N, k] array as stored, normalised) of a node's attributes, in the order written."""
    q = np.asarray(g.quats, np.float64)
    q = (q / np.sqrt(np.einsum("ij,ij->i", q, q))[:, None])[:, [1, 2, 3, 0]]        # unit in float64, then float32
    opacity = sigmoid(np.asarray(g.opacity_logits, np.float32))
    dc = np.clip(np.float32(0.5) + np.float32(SH_C0) * np.asarray(g.sh[:, 0, :], np.float32), 0.0, 1.0)
    colour = np.concatenate([srgb_to_linear(dc), opacity[:, None]], axis=1)
    out = [("POSITION", np.asarray(g.means, np.float32), False),
           (f"{EXTENSION}:ROTATION", q.astype(np.float32), False),
           (f"{EXTENSION}:SCALE", np.exp(np.asarray(g.log_scales, np.float32)), False),
           (f"{EXTENSION}:OPACITY", opacity[:, None], False)]
    for degree in range(g.sh_degree + 1):
        for n in range(2 * degree + 1):
            out.append((attribute_name(degree, n), np.asarray(g.sh[:, degree * degree + n, :], np.float32), False))
    out.append(("COLOR_0", np.floor(colour * 255.0 + 0.5).astype(np.uint8), True))
    return out


def document(nodes: Sequence[SplatNode], root: str, extras: Mapping[str, Any] | None = None
             ) -> tuple[dict[str, Any], list[np.ndarray]]:
    """(the glTF JSON, the buffer's parts in order, each 4-byte aligned) of one scene: a root node named ``root``
    (with ``extras``) whose children are ``nodes``; a node without Gaussians is left out. GltfError when none
    has any, or for a repeated name."""
    names = [nd.name for nd in nodes]
    if len(set(names)) != len(names):
        raise GltfError("nodes", f"node names must be unique (got {names})")
    kept = [nd for nd in nodes if len(nd.gaussians)]
    if not kept:
        raise GltfError("gaussians", "nothing to write: no node has Gaussians")
    from xyzcyl.common.version import __version__ as version

    accessors: list[dict] = []
    views: list[dict] = []
    meshes: list[dict] = []
    gnodes: list[dict] = [{"name": root, "children": list(range(1, len(kept) + 1)), **(
        {"extras": dict(extras)} if extras else {})}]
    parts: list[np.ndarray] = []
    offset = 0
    for nd in kept:
        attributes = {}
        for semantic, a, normalised in _columns(nd.gaussians):
            a = np.ascontiguousarray(a)
            views.append({"buffer": 0, "byteOffset": offset, "byteLength": a.nbytes, "target": _ARRAY_BUFFER})
            acc = {"bufferView": len(views) - 1, "componentType": _UBYTE if normalised else _FLOAT,
                   "count": len(a), "type": {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[a.shape[1]]}
            if normalised:
                acc["normalized"] = True
            if semantic == "POSITION":           # a column at a time (numpy's axis-0 reduction is slow for [N, 3])
                acc["min"] = [float(a[:, c].min()) for c in range(3)]
                acc["max"] = [float(a[:, c].max()) for c in range(3)]
            accessors.append(acc)
            attributes[semantic] = len(accessors) - 1
            parts.append(a)
            offset += a.nbytes                  # every element is 4 bytes or a multiple: stays 4-byte aligned
        meshes.append({"name": nd.name, "primitives": [{
            "attributes": attributes, "mode": _POINTS,
            "extensions": {EXTENSION: {"kernel": "ellipse", "colorSpace": COLOR_SPACE}}}]})
        node: dict[str, Any] = {"name": nd.name, "mesh": len(meshes) - 1}
        if nd.matrix is not None:
            M = np.asarray(nd.matrix, np.float64)
            if M.shape != (4, 4) or not np.isfinite(M).all() or not np.allclose(M[3], [0, 0, 0, 1]):
                raise GltfError(f"{nd.name}.matrix", "must be a finite [4, 4] affine matrix")
            if not np.array_equal(M, np.eye(4)):                  # the identity is glTF's default: not written
                node["matrix"] = [float(x) for x in M.T.ravel()]       # column-major
        if nd.extras:
            node["extras"] = dict(nd.extras)
        gnodes.append(node)
    doc = {"asset": {"version": "2.0", "generator": f"xyzcyl {version}"},
           "extensionsUsed": [EXTENSION], "scene": 0, "scenes": [{"name": root, "nodes": [0]}],
           "nodes": gnodes, "meshes": meshes, "accessors": accessors, "bufferViews": views,
           "buffers": [{"byteLength": offset}]}
    return doc, parts


def _json_bytes(doc: Mapping[str, Any]) -> bytes:
    return json.dumps(doc, separators=(",", ":"), allow_nan=False).encode()


def glb_chunks(doc: Mapping[str, Any], parts: Sequence[np.ndarray]) -> Iterator[bytes]:
    """The .glb of ``document``'s output, piece by piece (the parts are not joined): the 12-byte header, the JSON
    chunk (padded with spaces to 4 bytes), the BIN chunk (its parts, padded with zeros)."""
    js = _json_bytes(doc)
    js += b" " * (-len(js) % 4)
    size = sum(p.nbytes for p in parts)
    pad = -size % 4
    yield struct.pack("<III", _GLB_MAGIC, 2, 12 + 8 + len(js) + 8 + size + pad)
    yield struct.pack("<II", len(js), _JSON) + js
    yield struct.pack("<II", size + pad, _BIN)
    for p in parts:
        yield memoryview(np.ascontiguousarray(p)).cast("B")
    yield b"\0" * pad


def gltf_text(doc: Mapping[str, Any], parts: Sequence[np.ndarray]) -> bytes:
    """The .gltf of ``document``'s output: the JSON with its buffer as a base64 data URI."""
    data = b"".join(memoryview(np.ascontiguousarray(p)).cast("B") for p in parts)
    d = dict(doc)
    d["buffers"] = [{"byteLength": len(data),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode("ascii")}]
    return _json_bytes(d)


def write(path: str | os.PathLike, doc: Mapping[str, Any], parts: Sequence[np.ndarray], binary: bool) -> int:
    """Write ``document``'s output to ``path`` as .glb (``binary``) or .gltf; its size in bytes."""
    size = 0
    with open(path, "wb") as f:
        for chunk in (glb_chunks(doc, parts) if binary else [gltf_text(doc, parts)]):
            f.write(chunk)
            size += len(chunk) if isinstance(chunk, bytes) else chunk.nbytes
    return size


__all__ = ["COLOR_SPACE", "EXTENSION", "GltfError", "SplatNode", "attribute_name", "document", "glb_chunks",
           "gltf_text", "srgb_to_linear", "write"]
