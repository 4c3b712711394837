"""A drive's camera layers: each keyframe's cameras' cells as each camera saw them (docs/inference.md, "Camera
layers").

A keyframe's cells are fused before they join the scene: a camera hands a surface to another that resolves it more
finely (the dedupe), and what another camera of the keyframe placed a little in front of a surface (within the
carving's tolerance: 15 % of the depth, 0.45 m at 3 m) stays in front of it. Seen from another pose that is the better
set; seen from the camera itself it is not: a close parked car and a shop front drawn by the neighbouring camera, at
its depth and from its angle, over what this camera saw (the PandaSet drive's right camera at its own pose: 26.0 dB,
front-right 22.4 dB; each camera's own cells drawn first: 32.0 and 27.4 dB; docs/results.md "Camera layers"). So a
drive keeps, for each keyframe and camera, the camera's cells that no other camera of the keyframe saw through
(runtime.detail.carve_details without the dedupe), split cells as their quarters, without what lies in a moving
object's box (drawn from its copy, runtime.actors): a view standing within CAMERA_LAYER_M of one of its primary
keyframe's cameras and looking within CAMERA_LAYER_DEG of its axis draws that camera's layer first, and the scene's
layers behind it (runtime.scene.Scene.render). Farther away the fused set is the better one (the synthetic drive at
5 m/s: views 0.5 m from a keyframe's camera +0.16 dB with its layer first, 1 m away -0.84 dB).

On disk: ``cameras/keyframe_NNN.ply`` per keyframe (a 3DGS PLY without nx ny nz), its cameras' cells camera after
camera; scene.json's ``camera_layers`` block names the cameras and, per keyframe, its file and each camera's run of
its rows ([start, count]). A loaded scene reads one camera's run when a view first needs it
(Gaussians.load_ply_rows) and keeps the last CACHE_LAYERS it used."""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import FieldError
from .render import GaussianError, Gaussians
from .render.gaussians import save_ply_parts
from .viewpoints import Recent, link_or_copy, ply_count

LAYERS_DIR = "cameras"
CACHE_LAYERS = 12           # camera layers a loaded scene keeps in memory (~40 MB each at 1920x1080, stride 2): two
                            # keyframes' six cameras, so that a camera moving along the drive reads each layer once
CAMERA_LAYER_M = 0.75       # metres: a view within this of a keyframe's camera (and CAMERA_LAYER_DEG of its axis)
                            # draws that camera's layer first. The synthetic drive at 5 m/s (keyframes 2 m apart):
                            # views 0.5 m away gained 0.16 dB with it, 1 m away lost 0.84 dB (the fused set holds
                            # the next keyframe's finer cells there)
CAMERA_LAYER_DEG = 30.0     # degrees between the view's optical axis and the camera's (a rig's cameras are >= 45
                            # degrees apart: at most one is chosen)


class CameraLayerError(FieldError):
    """A scene's camera_layers block or a layer's file is invalid: ``field`` names the entry."""


@dataclass(frozen=True)
class KeyframeLayers:
    """One keyframe's camera layers: ``file`` (relative to the scene folder) holds them camera after camera;
    ``runs`` [camera] = (first row, rows)."""

    file: str
    runs: tuple[tuple[int, int], ...]

    @property
    def count(self) -> int:
        return sum(n for _, n in self.runs)

    def to_dict(self) -> dict[str, Any]:
        return {"file": self.file, "runs": [list(r) for r in self.runs]}


class CameraLayers:
    """A drive scene's camera layers (module docstring), read from ``folder`` (a scene folder, or the temporary
    folder a reconstruction writes them to as its keyframes come: ``tmp``, kept alive with them), one camera's run at
    a time (thread-safe: the service renders views of one scene on several threads)."""

    def __init__(self, cameras: Sequence[str], keyframes: Sequence[KeyframeLayers], folder: Path, tmp: Any = None):
        self.cameras = tuple(cameras)
        self.keyframes = list(keyframes)
        self._folder = Path(folder)
        self._tmp = tmp
        self._cache = Recent()
        self._writer: ThreadPoolExecutor | None = None      # add's thread, and the write it is doing
        self._pending: Future | None = None

    @classmethod
    def spill(cls, cameras: Sequence[str], tmp) -> CameraLayers:
        """Empty, written into the temporary folder ``tmp`` (a tempfile.TemporaryDirectory) by ``add``."""
        (Path(tmp.name) / LAYERS_DIR).mkdir(exist_ok=True)
        return cls(cameras, [], Path(tmp.name), tmp)

    def add(self, layers: Sequence[Sequence[Gaussians]]) -> None:
        """The next keyframe's layers: per camera (the rig's order), the parts of its layer (written one after the
        other, never joined: runtime.render.gaussians.save_ply_parts), on a thread of their own while the caller
        goes on (the fusion of the next keyframe: a keyframe's layers are ~200 MB); at most one keyframe's wait
        (``finish`` waits for the last and raises what a write raised)."""
        if len(layers) != len(self.cameras):
            raise ValueError(f"layers: one list of parts per camera ({len(self.cameras)}), got {len(layers)}")
        file = f"{LAYERS_DIR}/keyframe_{len(self.keyframes):03d}.ply"
        parts = [p for cam in layers for p in cam if len(p)]
        runs, at = [], 0
        for cam in layers:
            n = sum(len(p) for p in cam)
            runs.append((at, n))
            at += n
        if self._pending is not None:
            self._pending.result()
        if self._writer is None:
            self._writer = ThreadPoolExecutor(1, thread_name_prefix="xyzcyl-camera-layers")
        # without normals (nx ny nz, zeros that no reader uses): a sixth of the drive's largest files; past the
        # page cache (runtime.directio: read once at the reconstruction's end, by Gaussians.read_ply_take)
        self._pending = self._writer.submit(save_ply_parts, self._folder / file, parts or [Gaussians.empty()],
                                            normals=False, direct=True)
        self.keyframes.append(KeyframeLayers(file, tuple(runs)))

    def finish(self) -> None:
        """Wait for the keyframe being written (add), raising what its write raised; the writing thread ends."""
        pending, self._pending = self._pending, None
        writer, self._writer = self._writer, None
        try:
            if pending is not None:
                pending.result()
        finally:
            if writer is not None:
                writer.shutdown()

    def __len__(self) -> int:
        return len(self.keyframes)

    @property
    def count(self) -> int:
        """The Gaussians of every layer."""
        return sum(k.count for k in self.keyframes)

    def layer(self, k: int, c: int) -> Gaussians:
        """Keyframe k's camera c's layer (the scene's frame): its run of the keyframe's file, read when first asked
        for (CameraLayerError naming the file when it cannot be)."""
        key = (int(k), int(c))
        if self._pending is not None:       # still being written (a reconstruction's scene)
            self.finish()
        kept = self._cache.get(key)
        if kept is not None:
            return kept
        entry = self.keyframes[k]
        start, n = entry.runs[c]
        path = self._folder / entry.file
        try:
            g = Gaussians.load_ply_rows(path, start, start + n)
        except (GaussianError, OSError) as e:
            raise CameraLayerError(f"camera_layers.keyframes[{k}]", f"{entry.file!r} rows {start}..{start + n}: "
                                                                     f"{e}", f"scene {str(self._folder)!r}") from None
        self._cache.put(key, g, CACHE_LAYERS)
        return g

    def to_json(self) -> dict[str, Any]:
        return {"dir": LAYERS_DIR, "cameras": list(self.cameras), "keyframes": [k.to_dict() for k in self.keyframes],
                "count": self.count,
                "about": "per keyframe and camera, the camera's cells as it saw them: a view near that camera draws "
                         "them first"}

    def save(self, folder: Path) -> None:
        """Put every layer's file into ``folder`` (a scene folder being written): linked or copied, not read."""
        self.finish()
        (folder / LAYERS_DIR).mkdir(exist_ok=True)
        for k in self.keyframes:
            link_or_copy(self._folder / k.file, folder / k.file)

    @classmethod
    def from_json(cls, block: Any, folder: Path, keyframes: int, cameras: Sequence[str]) -> CameraLayers:
        """A scene folder's camera layers (scene.json's block) for ``keyframes`` keyframes of the rig's ``cameras``:
        each entry checked and its file's header read (CameraLayerError naming the entry); the layers are read
        when first used."""
        where = f"scene {str(folder)!r}"
        if not isinstance(block, dict):
            raise CameraLayerError("camera_layers", "must be an object", where)
        if block.get("cameras") != list(cameras):
            raise CameraLayerError("camera_layers.cameras", f"must be the rig's cameras {list(cameras)} (got "
                                                            f"{block.get('cameras')!r:.200})", where)
        entries = block.get("keyframes")
        if not isinstance(entries, list) or len(entries) != keyframes:
            raise CameraLayerError("camera_layers.keyframes", f"must be a list of the drive's {keyframes} keyframes",
                                   where)
        out = []
        for i, e in enumerate(entries):
            name = f"camera_layers.keyframes[{i}]"
            f = e.get("file") if isinstance(e, dict) else None
            runs = e.get("runs") if isinstance(e, dict) else None
            if not isinstance(f, str) or not f.startswith(LAYERS_DIR + "/") or ".." in Path(f).parts:
                raise CameraLayerError(f"{name}.file", f"must be a file in {LAYERS_DIR}/ (got {f!r:.200})", where)
            ok = isinstance(runs, list) and len(runs) == len(cameras) and all(
                isinstance(r, list) and len(r) == 2 and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0
                                                            for v in r) for r in runs)
            at = 0
            for r in runs if ok else ():
                ok = ok and r[0] == at
                at += r[1] if ok else 0
            if not ok:
                raise CameraLayerError(f"{name}.runs", f"must be one [start, count] per camera ({len(cameras)}), "
                                                       f"each starting where the one before ends (got {runs!r:.200})",
                                       where)
            have = ply_count(folder / f, f"{name}.file", CameraLayerError, where)
            if have != at:
                raise CameraLayerError(f"{name}.runs", f"{str(folder / f)!r} holds {have} Gaussians, the runs {at}",
                                       where)
            out.append(KeyframeLayers(f, tuple((int(a), int(n)) for a, n in runs)))
        return cls(cameras, out, folder)


__all__ = ["CACHE_LAYERS", "CAMERA_LAYER_DEG", "CAMERA_LAYER_M", "LAYERS_DIR", "CameraLayerError", "CameraLayers",
           "KeyframeLayers"]
