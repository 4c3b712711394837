"""A scene folder in another tool's format: `xyzcyl export` and GET /v1/scenes/{id}/export (docs/api.md, docs/cli.md).

Formats (FORMATS): ``usdz`` an AlpaSim scene artifact (runtime.usdz: every frame, tracks, a ground mesh);
``gltf`` / ``glb`` glTF 2.0 with KHR_gaussian_splatting (runtime.gltf), the static scene as one node and a drive's
actors each as its own node at a time; ``spz`` Niantic's compressed splats (runtime.spz); ``ply`` the 3DGS PLY and
``splat`` antimatter15's .splat (runtime.render.Gaussians' writers, GET .../gaussians' files).

A drive is exported as it is at a time T (seconds on the rigs' clock; default its first frame): glTF places each
actor drawn then (runtime.actors.Actors.placements) as a node whose matrix is its box pose then and whose Gaussians
are its copy nearest T in its box frame; the single-cloud formats (spz, ply, splat) bake those actors into the one
cloud (runtime.scene.Scene.moving_at). A scene without actors is the same at every time.

Frames, converted here and only here (docs/conventions.md "Exchange formats"): glTF is +Y up, +Z forward, +X left
(EGO_TO_GLTF: the ego's y, z, x), SPZ is RUB, x right, y up, z back (EGO_TO_SPZ: -y, z, -x), both in the data
(positions, rotations and SH bands turned: in_axes), so three.js, Spark and other viewers show the scene upright
with no root transform; PLY and .splat stay in the scene's ego frame (x forward, y left, z up), as GET .../gaussians
serves them."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import FieldError
from .render import Gaussians

FORMATS = ("usdz", "gltf", "glb", "spz", "ply", "splat")
MEDIA_TYPES = {"usdz": "model/vnd.usdz+zip", "gltf": "model/gltf+json", "glb": "model/gltf-binary",
               "spz": "application/octet-stream", "ply": "application/x-ply", "splat": "application/x-splat"}
# the version of what each format's file holds, in the HTTP ETag (runtime.usdz.FORMAT_VERSION for usdz): raised
# when a change of this module changes the bytes of an export of the same scene
FORMAT_VERSION = 1
SINGLE_CLOUD = ("spz", "ply", "splat")

# [3, 3] ego (x forward, y left, z up) -> the format's axes; rows: the format's x, y, z in ego coordinates
EGO_TO_GLTF = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])       # +X left, +Y up, +Z forward
EGO_TO_SPZ = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])      # RUB: x right, y up, z back
_SH_DIRS = 64                      # sample directions fitting an SH rotation (16 coefficients: exact, over-determined)


class ExportError(FieldError):
    """A scene that cannot be exported as asked (``field``: "format", "time", "scene_id", "out", "gaussians")."""


@dataclass(frozen=True)
class ExportReport:
    """What an export wrote: the file, its format and size (bytes), the Gaussians in it, the actors placed (as
    nodes, or baked into the cloud) at ``time_s`` (None: a scene without a drive), the seconds it took, notes."""

    path: Path
    format: str
    bytes: int
    gaussians: int
    actors: tuple[str, ...]
    time_s: float | None
    seconds: float
    notes: tuple[str, ...] = field(default_factory=tuple)

    def to_json(self) -> dict[str, Any]:
        return {"path": str(self.path), "format": self.format, "bytes": self.bytes, "gaussians": self.gaussians,
                "actors": list(self.actors), "time_s": self.time_s, "seconds": round(self.seconds, 3),
                "notes": list(self.notes)}


# ------------------------------------------------------------------------------------------------- frames
def rotate_sh(sh: np.ndarray, R: np.ndarray) -> np.ndarray:
    """[N, K, 3] SH coefficients (runtime/render/sh.py's basis) of colours defined on directions in a frame ->
    the same colours' coefficients in the frame that ``R`` [3, 3] (a rotation) maps that one to. Each band turns by
    its own K_l x K_l matrix, fitted on fixed sample directions (exact: a band's span is closed under rotation)."""
    from .render.sh import sh_basis

    sh = np.asarray(sh)
    k = sh.shape[1]
    if k == 1:
        return sh
    i = np.arange(_SH_DIRS) + 0.5                                   # Fibonacci sphere
    z = 1.0 - 2.0 * i / _SH_DIRS
    phi = np.pi * (1.0 + 5.0 ** 0.5) * i
    d = np.stack([np.sqrt(1.0 - z * z) * np.cos(phi), np.sqrt(1.0 - z * z) * np.sin(phi), z], axis=1)
    # a direction d in the new frame is R^T d in the old: B(d) M = B(R^T d), rows d^T R
    M = np.linalg.lstsq(sh_basis(d, k), sh_basis(d @ np.asarray(R, np.float64), k), rcond=None)[0]
    M[np.abs(M) < 1e-12] = 0.0
    return np.einsum("jk,nkc->njc", M, sh.astype(np.float64)).astype(sh.dtype)


def axes_matrix(R: np.ndarray) -> np.ndarray:
    """[4, 4] the rotation [3, 3] ``R`` as a homogeneous transform."""
    T = np.eye(4)
    T[:3, :3] = R
    return T


def left_product(q: np.ndarray) -> np.ndarray:
    """[4, 4] L with L @ p = q p (the Hamilton product, wxyz) for the quaternion ``q`` [4]."""
    w, x, y, z = np.asarray(q, np.float64)
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def in_axes(g: Gaussians, R: np.ndarray) -> Gaussians:
    """Gaussians ``g`` with their frame's axes turned by ``R`` [3, 3] (EGO_TO_GLTF, EGO_TO_SPZ): means, rotations (the
    turn's quaternion times each) and SH bands; scales and opacities unchanged. In the Gaussians' dtype, one matrix
    product per field (Gaussians.transformed's float64 arithmetic took 2 s for 3 M)."""
    from .rotations import rotmats_to_quats

    R = np.asarray(R, np.float64)
    dt = g.means.dtype
    L = left_product(rotmats_to_quats(R[None])[0])
    return Gaussians(g.means @ R.T.astype(dt), g.quats @ L.T.astype(g.quats.dtype), g.log_scales, g.opacity_logits,
                     rotate_sh(g.sh, R))


# ------------------------------------------------------------------------------------------------- the scene
@dataclass(frozen=True)
class Placed:
    """One actor drawn at the export's time: its id and label, its Gaussians in its box frame (x along its length,
    y left, z up; metres) and ``pose`` [4, 4] box -> scene frame then."""

    id: str
    label: str
    gaussians: Gaussians
    pose: np.ndarray


def actors_at(scene, time_s: float | None) -> tuple[float | None, list[Placed]]:
    """(the time used: ``time_s``, default the drive's first frame, None for a scene without a drive; the actors
    drawn then, each at its recorded pose: runtime.actors.Actors.placements without edits)."""
    t = scene.start_time() if time_s is None else float(time_s)
    a = scene.actors
    if a is None or t is None:
        return t, []
    out = []
    for i, T in a.placements(t, 0.5 * scene.frame_interval()):
        g = a.copy_of(i, t)
        if len(g):
            out.append(Placed(a.track_id[i], a.track_label[i], g, np.asarray(T, np.float64)))
    return t, out


def gltf_document(scene, name: str, time_s: float | None = None):
    """(the glTF JSON, its buffer's parts, the time used, the actors placed) of ``scene`` (runtime.gltf.document):
    the static scene as node "static", each actor drawn at the time as node "actor:<id>" (its Gaussians in its box
    frame, its matrix the box pose then), everything in glTF's axes."""
    from .gltf import SplatNode, document

    t, placed = actors_at(scene, time_s)
    C = axes_matrix(EGO_TO_GLTF)
    nodes = [SplatNode("static", in_axes(scene.gaussians, EGO_TO_GLTF), extras={"part": "static scene"})]
    for p in placed:
        nodes.append(SplatNode(f"actor:{p.id}", in_axes(p.gaussians, EGO_TO_GLTF), C @ p.pose @ C.T,
                               extras={"actor": p.id, "label": p.label}))
    extras = {"frame": "glTF: +X left, +Y up, +Z forward (the scene's ego frame's y, z, x), metres"}
    if t is not None:
        extras["time_s"] = t
    doc, parts = document(nodes, name, extras)
    return doc, parts, t, placed


def one_cloud(scene, time_s: float | None = None) -> tuple[Gaussians, float | None, tuple[str, ...]]:
    """(the static scene with the actors drawn at the time baked in, scene frame, as a render draws them:
    runtime.actors.Actors.at; the time used, as actors_at; the ids of those actors)."""
    from .detail import concat_gaussians

    t = scene.start_time() if time_s is None else float(time_s)
    if scene.actors is None or t is None:
        return scene.gaussians, t, ()
    moving, drawn = scene.actors.at(t, 0.5 * scene.frame_interval())
    if not len(moving):
        return scene.gaussians, t, ()
    return concat_gaussians([scene.gaussians, moving]), t, tuple(scene.actors.track_id[a] for a in drawn)


def check_request(fmt: str, time_s: float | None, scene_id: str | None) -> str:
    """The format, lower-cased, of a valid request (ExportError naming the field otherwise): a known format; a
    finite ``time_s`` and no time for usdz (its artifact holds every frame); a scene id only for usdz, gltf and glb
    (SPZ, PLY and .splat carry no name)."""
    f = str(fmt).lower()
    if f not in FORMATS:
        raise ExportError("format", f"{fmt!r} is not one of {', '.join(FORMATS)}")
    if time_s is not None:
        if not np.isfinite(time_s):
            raise ExportError("time", f"must be a finite number of seconds (got {time_s})")
        if f == "usdz":
            raise ExportError("time", "a USDZ artifact holds every frame of the drive: no time for usdz")
    if scene_id is not None and f in SINGLE_CLOUD:
        raise ExportError("scene_id", f"a {f} file carries no name (usdz, gltf and glb do)")
    return f


def write_scene(scene, out: str | os.PathLike, fmt: str, time_s: float | None = None, name: str = "scene",
                progress: Callable[[str], None] | None = None) -> ExportReport:
    """Write loaded ``scene`` (runtime.scene.Scene) to ``out`` as ``fmt`` (not usdz: export_scene), atomically (a
    temporary file beside it, then a rename): the report. ``name``: the glTF root node's and scene's name."""
    from .gltf import write
    from .spz import spz_bytes

    fmt = check_request(fmt, time_s, None)
    if fmt == "usdz":
        raise ExportError("format", "usdz is written from the scene folder (export_scene)")
    say = progress or (lambda msg: None)
    out = Path(out)
    start = time.perf_counter()
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    notes: list[str] = []
    try:
        if fmt in ("gltf", "glb"):
            doc, parts, t, placed = gltf_document(scene, name, time_s)
            n = sum(len(p.gaussians) for p in placed) + len(scene.gaussians)
            ids = tuple(p.id for p in placed)
            say(f"writing {n:,} Gaussians as {fmt} ({len(ids)} actors as nodes)")
            size = write(tmp, doc, parts, binary=fmt == "glb")
        else:
            g, t, ids = one_cloud(scene, time_s)
            if ids:
                notes.append(f"{len(ids)} actors baked into the cloud at {t:.3f} s (a {fmt} file is one cloud)")
            say(f"writing {len(g):,} Gaussians as {fmt}")
            if fmt == "spz":
                tmp.write_bytes(spz_bytes(in_axes(g, EGO_TO_SPZ)))
            elif fmt == "ply":
                g.save_ply(tmp)
            else:
                g.save_splat(tmp)
            size, n = tmp.stat().st_size, len(g)
        os.replace(tmp, out)
        if scene.drive and t is not None:
            times, _ = scene.timeline()
            slack = 0.5 * scene.frame_interval()
            if not times[0] - slack <= t <= times[-1] + slack:
                notes.append(f"{t:.3f} s is outside the drive ({times[0]:.3f}..{times[-1]:.3f} s): no actor is "
                             "drawn then")
    finally:
        if tmp.exists():
            tmp.unlink()
    return ExportReport(path=out, format=fmt, bytes=size, gaussians=n, actors=ids,
                        time_s=t, seconds=time.perf_counter() - start, notes=tuple(notes))


def export_scene(folder: str | os.PathLike, out: str | os.PathLike, fmt: str, time_s: float | None = None,
                 scene_id: str | None = None, progress: Callable[[str], None] | None = None):
    """Export the scene folder ``folder`` to ``out`` as ``fmt``: usdz through runtime.usdz.export_usdz (its
    UsdzReport), the others through write_scene (an ExportReport; ``scene_id`` names glTF's root node, default the
    folder's name). ExportError / runtime.usdz.UsdzError / runtime.scene.SceneError name what is wrong."""
    from .scene import Scene

    fmt = check_request(fmt, time_s, scene_id)
    if fmt == "usdz":
        from .usdz import export_usdz

        return export_usdz(folder, out, scene_id, progress=progress)
    scene = Scene.load(folder)
    return write_scene(scene, out, fmt, time_s, scene_id or Path(folder).resolve().name, progress)


__all__ = ["EGO_TO_GLTF", "EGO_TO_SPZ", "FORMATS", "FORMAT_VERSION", "MEDIA_TYPES", "ExportError", "ExportReport",
           "Placed", "actors_at", "axes_matrix", "check_request", "export_scene", "gltf_document", "in_axes",
           "left_product", "one_cloud", "rotate_sh", "write_scene"]
