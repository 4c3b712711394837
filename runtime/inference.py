"""The torch-free inference path: a model folder (ONNX graphs exported by xyzcyl.model_export.export) run by
onnxruntime turns a rig of images into a Scene (runtime.scene). docs/inference.md describes the whole path.

    rec = Reconstructor.load("models/xyzcyl-cpu-v1", threads=2)   # checks every file's sha256
    scene = rec.reconstruct(load_rig("rig.json"))                   # images (and depth files) from the rig
    scene.save("/tmp/scene")

Stages (timed in scene.timings): decode (image files), resize (cv2.INTER_AREA to the model's input; calibrations
need no change since the lifting grids are normalised image coordinates), lifting (runtime.lifting, cached per
rig calibration), encode (graph), select (numpy voxel selection), volume (graph), gaussians (assembly, pruning of
invisible Gaussians), background (the background graph baked into a panorama on the cylinder).

A Reconstructor is safe to use from several threads: onnxruntime sessions run concurrently and the lifting
cache is locked.
"""

from __future__ import annotations

import hashlib
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .camera import Camera
from .detail import CameraDetail, DetailOptions, fuse_details
from .errors import FieldError, RigError
from .lifting import background_grid, build_lifting_inputs, spec_from_array
from .model_folder import (  # re-exported: part of runtime.inference's API before runtime/model_folder.py
    MODEL_FORMAT,
    ModelError,
    ModelInfo,
    _sha256,
    default_model_dir,
    read_model_file,
    read_model_info,
    verify_model,
)
from .numba_cache import threadsafe
from .render import FIELDS, Gaussians
from .rig import Rig
from .scene import Background, Scene, bake_grid
from .threads import in_threads, one_blas_thread

GAUSSIAN_KEYS = FIELDS
# a Gaussian whose opacity is below this never contributes (the renderer skips alpha < 1/255 and alpha <= o);
# 0.99: margin for float rounding between numpy's and the kernel's sigmoid
PRUNE_OPACITY = 0.99 / 255.0
DEFAULT_BAKE_SCALE = 4
DEFAULT_DETAIL = DetailOptions()   # the detail layer is on by default (docs/inference.md, "Detail Gaussians")
DETAIL_THREADS = 2                 # cameras whose detail layer is made at once (Reconstructor.camera_details)
PREPARE_THREADS = 2                # cameras whose image is converted (as_rgb) and resized at once: numpy's conversion
#                                    and OpenCV's resize run outside the GIL (Reconstructor.prepare, rgb_of, rgb_images)
# the encode graph split where the depth enters (model_export.split): both halves in model.json, the runtime runs
# them in turn instead of "encode" and a second pass with another depth (LiDAR) runs only the second
ENCODE_SPLIT = ("encode_image", "encode_depth")


class InferenceError(FieldError):
    """An input cannot be reconstructed: ``field`` the input at fault ("lidar", "background")."""


# ------------------------------------------------------------------------------------------- inputs


def calibration_key(rig: Rig) -> str:
    """sha256 over each camera's model, size, K, cam_to_ego and distortion, in rig order (the lifting inputs
    depend on nothing else)."""
    h = hashlib.sha256()
    for c in rig.cameras:
        h.update(f"{c.model}|{c.width}|{c.height}|{c.distortion}|".encode())
        h.update(np.ascontiguousarray(c.K if c.K is not None else np.zeros((3, 3)), np.float64).tobytes())
        h.update(np.ascontiguousarray(c.cam_to_ego, np.float64).tobytes())
    return h.hexdigest()


def as_rgb(img: np.ndarray, cam: Camera) -> np.ndarray:
    """An image array -> [H, W, 3] float32 in 0..1 (uint8/uint16 scaled, grey replicated, alpha dropped);
    RigError naming the camera for a bad shape or non-finite values."""
    a = np.asarray(img)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[:2] != (cam.height, cam.width) or a.shape[2] not in (1, 3, 4):
        raise RigError("image", f"has shape {list(np.shape(img))}, but the rig declares "
                       f"{cam.width}x{cam.height} (width x height) RGB", cam.where)
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    a = a[..., :3]
    if np.issubdtype(a.dtype, np.integer):
        out = a.astype(np.float32)          # a new array (the caller's stays as it is), scaled in place
        out /= float(np.iinfo(a.dtype).max)
    elif np.issubdtype(a.dtype, np.floating):
        # one pass to check (a NaN or an inf makes the float64 sum non-finite; float32 values cannot overflow it),
        # one to clip into a new array (the caller's stays as it is)
        if not np.isfinite(a.sum(dtype=np.float64)):
            raise RigError("image", "has non-finite values", cam.where)
        out = np.clip(a, 0.0, 1.0, dtype=np.float32)
    else:
        raise RigError("image", f"dtype {a.dtype} is not a number type", cam.where)
    return np.ascontiguousarray(out)


class RgbImages(list):
    """A rig's images already made [H, W, 3] float32 0..1 by as_rgb, in rig order (rgb_of): Reconstructor.prepare
    and camera_details take them as they are instead of converting (and checking) each again."""


def rgb_images(rig: Rig, threads: int = 1) -> RgbImages:
    """Each camera's image file of ``rig`` as as_rgb makes it ([H, W, 3] float32 0..1), in the rig's camera order:
    decoded in the file's own type and converted once (an 8-bit file's pixels / 255 in place: no float copy to
    check and clip again), ``threads`` cameras at a time (the decoder and numpy release the GIL)."""
    return RgbImages(in_threads(lambda k: as_rgb(rig.load_image(k, native=True), rig.cameras[k]),
                                range(len(rig.cameras)), threads))


def rgb_of(rig: Rig, images: Sequence[np.ndarray], threads: int = 1) -> RgbImages:
    """as_rgb of each camera's image (``threads`` cameras at a time: numpy's conversion runs outside the GIL)."""
    if isinstance(images, RgbImages):
        return images
    if len(images) != len(rig.cameras):
        raise RigError("images", f"{len(rig.cameras)} cameras but {len(images)} images", "rig")
    return RgbImages(in_threads(lambda k: as_rgb(images[k], rig.cameras[k]), range(len(images)), threads))


def resize_area(img: np.ndarray, height: int, width: int) -> np.ndarray:
    """cv2.INTER_AREA resize of [H, W, C] float32 (identity at the same size)."""
    if img.shape[:2] == (height, width):
        return img
    import cv2

    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)


def resize_nearest(a: np.ndarray, height: int, width: int) -> np.ndarray:
    """[H, W] -> [height, width] with torch's F.interpolate(mode='nearest') rule: src = floor(dst * in / out)
    (float32), clamped -- the rule XYZCylinder's depth head applies to a supplied depth map."""
    H, W = a.shape
    r = np.minimum(np.floor(np.arange(height, dtype=np.float32) * np.float32(H / height)).astype(np.int64), H - 1)
    c = np.minimum(np.floor(np.arange(width, dtype=np.float32) * np.float32(W / width)).astype(np.int64), W - 1)
    return a[r[:, None], c[None, :]]


def check_depth(d: np.ndarray, cam: Camera) -> np.ndarray:
    """A supplied depth map [H, W] (metres, the camera's depth: along the optical axis for a pinhole or an opencv
    lens, along the pixel's ray from the camera centre for a fisheye or f-theta lens, Camera.depth_is_distance) ->
    float32; RigError naming the camera when its size differs from the camera's, or it has NaN/inf or negative
    values."""
    a = np.asarray(d)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2 or a.shape != (cam.height, cam.width):
        raise RigError("depth", f"has shape {list(np.shape(d))}, but the rig declares "
                       f"{cam.width}x{cam.height} (width x height)", cam.where)
    a = a.astype(np.float32)
    bad = int(np.count_nonzero(~np.isfinite(a)))
    if bad:
        raise RigError("depth", f"has {bad} non-finite (NaN/inf) values", cam.where)
    if (a < 0).any():
        raise RigError("depth", "has negative values", cam.where)
    return a


def select_voxels(occ_logits: np.ndarray, max_voxels: int) -> np.ndarray:
    """XYZCylinder.select_voxels (predicted) in numpy: flat indices [M] int64 of the voxels with
    occ_logits[1] > occ_logits[0]; when more than ``max_voxels``, the ``max_voxels`` largest margins (descending,
    ties in index order)."""
    margin = (occ_logits[1] - occ_logits[0]).reshape(-1)
    idx = np.flatnonzero(margin > 0)
    if idx.size > max_voxels:
        idx = idx[np.argsort(-margin[idx], kind="stable")[:max_voxels]]
    return idx.astype(np.int64)


# ------------------------------------------------------------------------------------------- reconstructor


def _session(data: bytes, threads: int | None, name: str, spin: bool = False):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads or 0)
    so.inter_op_num_threads = 1
    # no busy-waiting between operators: measured 0.54 s instead of 0.80 s per encode on two shared cores (a server
    # runs renders and other sessions beside it); spinning may help on an otherwise idle machine (not measured)
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin else "0")
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3
    try:
        return ort.InferenceSession(data, so, providers=["CPUExecutionProvider"])
    except Exception as e:  # noqa: BLE001 -- onnxruntime raises its own exception types
        raise ModelError("model", f"file {name!r}: onnxruntime cannot load it ({e})") from None


@dataclass
class Keyframe:
    """One timestamp reconstructed up to the fusion of its cameras' detail layers (Reconstructor.keyframe), in its
    rig's ego frame: the model's Gaussians (``coarse``), per pinhole camera its detail Gaussians (``parts``), cell
    maps (``details``, runtime.detail.CameraDetail) and rig index (``owners``); counts and stage seconds so far; the
    background panorama (or None); ``started``: time.perf_counter() when it began."""

    coarse: Gaussians
    parts: list[Gaussians]
    details: list[CameraDetail]
    owners: list[int]
    counts: dict[str, int]
    timings: dict[str, float]
    background: Background | None
    app_plane: np.ndarray | None
    lifting_cached: bool
    started: float


def scene_model_of(info: ModelInfo) -> dict[str, str]:
    """What a scene records of the model folder ``info`` (model.json's name, version and sha256): without loading
    its sessions (`xyzcyl batch` stamps and fuses scenes in processes that hold no model)."""
    return {"name": info.name, "version": info.version,
            "model_json_sha256": _sha256((info.path / "model.json").read_bytes())}


class Reconstructor:
    """One model folder's onnxruntime sessions and a cache of lifting inputs per rig calibration."""

    def __init__(self, info: ModelInfo, sessions: Mapping[str, Any], threads: int | None, cache_size: int = 8,
                 bake_scale: int = DEFAULT_BAKE_SCALE):
        self.info = info
        self.sessions = dict(sessions)
        self.threads = threads
        self.cache_size = int(cache_size)
        self.bake_scale = int(bake_scale)
        self._cache: OrderedDict[str, dict[str, np.ndarray]] = OrderedDict()
        self._lock = threading.Lock()
        self._params = info.lifting

    @classmethod
    def load(cls, model_dir: str | os.PathLike, threads: int | None = None, cache_size: int = 8,
             verify: bool = True, bake_scale: int = DEFAULT_BAKE_SCALE, spin: bool = False) -> Reconstructor:
        """Read model.json, check the sha256 of every listed file (ModelError naming a missing or altered file),
        create one onnxruntime session per graph with ``threads`` intra-op threads (None: onnxruntime's default,
        all cores; ``spin``: let idle threads busy-wait, faster only on an otherwise idle machine). Limits numpy's
        BLAS to one thread in this process (runtime.threads)."""
        if threads is not None and int(threads) < 1:
            raise ValueError(f"threads: must be >= 1, got {threads}")
        one_blas_thread()           # its idle threads would wait on the reconstruction's cores (runtime.threads)
        info = read_model_info(model_dir)
        blobs = {name: read_model_file(info, name, verify) for name in info.meta["files"]}
        sessions = {}
        graphs = info.meta["graphs"]
        split = all(g in graphs for g in ENCODE_SPLIT)
        for g, entry in graphs.items():
            if entry["file"] not in blobs:
                raise ModelError(f"graphs.{g}.file", f"{entry['file']!r} is not listed in files", "model")
            if g == "encode" and split:
                continue    # its halves compute it: no session of its own (its set-up took 1.2 s, both halves' 0.75 s)
            sessions[g] = _session(blobs[entry["file"]], threads, entry["file"], spin)
        if "encode" not in graphs:
            raise ModelError("graphs", f"{info.path / 'model.json'} has no 'encode' graph", "model")
        return cls(info, sessions, threads, cache_size, bake_scale)

    # -- lifting inputs ---------------------------------------------------------------------------------------
    def lifting(self, rig: Rig) -> tuple[dict[str, np.ndarray], bool]:
        """(lifting inputs of ``rig``, whether they came from the cache)."""
        key = calibration_key(rig)
        with self._lock:
            hit = self._cache.get(key)
            if hit is not None:
                self._cache.move_to_end(key)
                return hit, True
        out = build_lifting_inputs(rig, self._params)
        for v in out.values():
            v.setflags(write=False)
        with self._lock:
            self._cache[key] = out
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return out, False

    # -- stages -------------------------------------------------------------------------------------------------
    def _run(self, graph: str, feed: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        if graph == "encode" and graph not in self.sessions:
            return self.encode(feed)[0]
        s = self.sessions[graph]
        names = [o.name for o in s.get_outputs()]
        outs = s.run(names, {i.name: feed[i.name] for i in s.get_inputs()})
        return dict(zip(names, outs))

    def encode(self, feed: Mapping[str, np.ndarray], image_part: Mapping[str, np.ndarray] | None = None
               ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
        """(the encode graph's outputs for ``feed``, the image half's outputs to pass back as ``image_part``). With
        the split graphs (ENCODE_SPLIT) the image half runs unless ``image_part`` (from an earlier call with the
        same images and lifting inputs: only the depth inputs may differ) is given, then the depth half; else the
        encode graph (image_part None)."""
        if "encode" in self.sessions:
            return self._run("encode", feed), None
        image, depth = ENCODE_SPLIT
        early = dict(image_part) if image_part is not None else self._run(image, feed)
        out = self._run(depth, {**feed, **early})
        return {o["name"]: (out[o["name"]] if o["name"] in out else early[o["name"]])
                for o in self.info.meta["graphs"]["encode"]["outputs"]}, early

    def prepare(self, rig: Rig, images: Sequence[np.ndarray], depths: Sequence[np.ndarray | None] | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Validated, resized network inputs: images [N, 3, H, W], depth [N, 1, h, w], depth_mask [N]. images: one
        per camera as reconstruct takes them, or an RgbImages (rgb_of: already converted, taken as they are)."""
        if len(images) != len(rig.cameras):
            raise RigError("images", f"{len(rig.cameras)} cameras but {len(images)} images", "rig")
        H, W = self.info.input_size
        rgb = images if isinstance(images, RgbImages) else None

        def small(k: int) -> np.ndarray:
            a = rgb[k] if rgb is not None else as_rgb(images[k], rig.cameras[k])
            return resize_area(a, H, W).transpose(2, 0, 1)

        imgs = np.stack(in_threads(small, range(len(images)), PREPARE_THREADS))
        h, w = self.info.depth_size
        depth = np.zeros((len(rig.cameras), 1, h, w), np.float32)
        mask = np.zeros(len(rig.cameras), np.float32)
        if depths is not None:
            if len(depths) != len(rig.cameras):
                raise RigError("depths", f"{len(rig.cameras)} cameras but {len(depths)} depth maps", "rig")
            for n, (d, cam) in enumerate(zip(depths, rig.cameras)):
                if d is None:
                    continue
                if cam.model != "pinhole":
                    raise RigError("depth", "is supported for pinhole cameras only", cam.where)
                depth[n, 0] = resize_nearest(check_depth(d, cam), h, w)
                mask[n] = 1.0
        return np.ascontiguousarray(imgs, np.float32), depth, mask

    def reconstruct(self, rig: Rig, images: Sequence[np.ndarray] | None = None,
                    depths: Sequence[np.ndarray | None] | None = None,
                    progress: Callable[[str], None] | None = None,
                    lidar: np.ndarray | None = None, detail: DetailOptions | None = DEFAULT_DETAIL,
                    exposure: bool = True) -> Scene:
        """Gaussians (ego frame), background and metadata of one timestamp of ``rig``.

        images: one [H, W, 3] array per camera in rig order (uint8, uint16 or float 0..1), or None to read the
        rig's image files; depths: per camera a [H, W] depth map in metres or None, or None for the rig's depth
        files (if any). lidar: [P, 3] metres, ego frame, a LiDAR sweep of the same timestamp: each pinhole camera
        without a depth map then gets one made from it (``lidar_depths``: two encode passes). detail: the detail
        layer's settings (runtime.detail; None = the model's Gaussians only). exposure: harmonise the cameras'
        exposure and white balance (runtime.exposure, as a drive's keyframe: each camera's detail cells divided by its
        gain, a view near an input camera drawn with its gain back; with the detail layer and two cameras or more).
        Errors name the camera (RigError) or the model file (ModelError)."""
        kf = self.keyframe(rig, images, depths, progress, lidar, detail, detail_threads=DETAIL_THREADS)
        gauss, own_views, gains = kf.coarse, None, None
        if kf.details:
            t0 = time.perf_counter()
            coarse, parts, details = kf.coarse, kf.parts, kf.details
            if exposure and len(kf.details) > 1:
                from .exposure import Harmoniser

                h = Harmoniser(len(rig.cameras))
                parts = h.add(kf.details, parts, kf.owners)
                details = h.details(kf.details, kf.owners)
                coarse = h.coarse(coarse)
                gains = h.to_json(rig.names)
                kf.timings["exposure"] = time.perf_counter() - t0
                t0 = time.perf_counter()
            gauss, own_views, fused = fuse_details(coarse, parts, details, kf.owners, tuple(rig.names),
                                                   detail)
            kf.counts.update(fused)
            kf.timings["detail"] += time.perf_counter() - t0
        kf.timings["total"] = time.perf_counter() - kf.started
        return Scene(gaussians=gauss, background=kf.background, rig=rig, model=self.scene_model(),
                     counts=kf.counts, timings={k: round(v, 6) for k, v in kf.timings.items()},
                     lifting_cached=kf.lifting_cached, app_plane=kf.app_plane, own_views=own_views, exposure=gains)

    def scene_model(self) -> dict[str, str]:
        """What a scene records of the model that made it: name, version, model.json's sha256."""
        return scene_model_of(self.info)

    def keyframe(self, rig: Rig, images: Sequence[np.ndarray] | None = None,
                 depths: Sequence[np.ndarray | None] | None = None,
                 progress: Callable[[str], None] | None = None,
                 lidar: np.ndarray | None = None, detail: DetailOptions | None = DEFAULT_DETAIL,
                 ego_masks: Mapping[str, np.ndarray] | None = None, lidar_is_sweep: bool = True,
                 detail_threads: int = 1) -> Keyframe:
        """One timestamp of ``rig`` up to, not including, the fusion of its cameras' detail layers (reconstruct's
        arguments): the model's Gaussians, each pinhole camera's detail Gaussians and cell maps, the background.
        reconstruct fuses one; runtime.drive fuses the keyframes of a drive. ego_masks: camera name -> [H, W] bool
        (True: the ego's own body, no cells there) for cameras whose rig gives no ego_mask file (runtime.egobody
        finds them over a drive). lidar_is_sweep=False: ``lidar`` holds sparse points triangulated between frames
        (runtime.stereo), not a sweep: the detail layer keeps the model's ground plane and trust (camera_details).
        detail_threads: cameras whose detail is made at once (camera_details; a drive makes its next keyframe while
        it fuses this one and keeps 1)."""
        say = progress or (lambda msg: None)
        t: dict[str, float] = {}
        t_all = time.perf_counter()
        if len(rig.cameras) > 16:
            raise RigError("cameras", f"at most 16 cameras, got {len(rig.cameras)}", "rig")
        t0 = time.perf_counter()
        if images is None:
            say("decode images")
            images = rgb_images(rig, PREPARE_THREADS)
        if depths is None and any(c.depth is not None for c in rig.cameras):
            depths = rig.load_depths()
        t["decode"] = time.perf_counter() - t0

        def timed(key: str, fn: Callable, *args):
            t0 = time.perf_counter()
            out = fn(*args)
            t[key] = time.perf_counter() - t0
            return out

        def inputs():
            rgb = rgb_of(rig, images, PREPARE_THREADS)      # once for the network's inputs and the detail layer
            return rgb, *self.prepare(rig, rgb, depths)

        rgb, imgs, depth, mask = timed("resize", inputs)
        lift, cached = timed("lifting", self.lifting, rig)
        say("encode")
        enc, image_part = timed("encode", self.encode, {"images": imgs, "depth": depth, "depth_mask": mask, **lift})
        gauss, counts = self._gaussians(enc, lift, t, say)
        if lidar is not None:
            say("LiDAR depth")
            depth, mask, scales = timed("lidar", self.lidar_depths, rig, gauss, lidar, depth, mask)
            say("encode with LiDAR depth")
            # the same images: with the split graphs only the depth half runs again
            enc, _ = timed("encode_lidar", self.encode, {"images": imgs, "depth": depth, "depth_mask": mask, **lift},
                           image_part)
            gauss, counts = self._gaussians(enc, lift, t, say)
            counts["lidar_cameras"] = int(sum(s is not None for s in scales))
        parts: list[Gaussians] = []
        details: list = []
        owners: list[int] = []
        if detail is not None:
            say(f"detail Gaussians (stride {detail.stride})")
            parts, details, owners = timed("detail", self.camera_details, rig, rgb, gauss, lidar, detail, counts,
                                           ego_masks, lidar_is_sweep, detail_threads)

        background = None
        app_plane = enc.get("app_plane")
        if app_plane is not None and "background" in self.sessions:
            say("background")
            t0 = time.perf_counter()
            background = self.bake_background(rig, app_plane)
            t["background"] = time.perf_counter() - t0
        return Keyframe(coarse=gauss, parts=parts, details=details, owners=owners, counts=counts, timings=t,
                        background=background, app_plane=app_plane, lifting_cached=cached, started=t_all)

    def _gaussians(self, enc: Mapping[str, np.ndarray], lift: Mapping[str, np.ndarray], t: dict[str, float],
                   say: Callable[[str], None]) -> tuple[Gaussians, dict[str, int]]:
        """The encode outputs -> the scene's Gaussians (volume graph on the selected voxels + pixel Gaussians,
        invisible ones pruned) and their counts; stage times go into ``t``."""
        parts: list[dict[str, np.ndarray]] = []
        n_vox = 0
        counts: dict[str, int] = {"volume": 0, "pixel": 0}
        if "volume" in self.sessions:
            t0 = time.perf_counter()
            idx = select_voxels(enc["occ_logits"], self.info.max_voxels)
            n_vox = int(idx.size)
            t["select"] = time.perf_counter() - t0
            say(f"volume ({n_vox} voxels)")
            t0 = time.perf_counter()
            vol = self._run("volume", {"geo_cpfg": enc["geo_cpfg"], "app_cpfg": enc["app_cpfg"], "voxel_idx": idx,
                                       "vol_coords": lift["vol_coords"], "voxel_centres": lift["voxel_centres"]})
            t["volume"] = time.perf_counter() - t0
            parts.append({k: vol[f"volume_{k}"] for k in GAUSSIAN_KEYS})
            counts["volume"] = int(vol["volume_means"].shape[0])
        if "pixel_means" in enc:
            parts.append({k: enc[f"pixel_{k}"] for k in GAUSSIAN_KEYS})
            counts["pixel"] = int(enc["pixel_means"].shape[0])

        t0 = time.perf_counter()
        g = {k: np.concatenate([p[k] for p in parts], axis=0).astype(np.float32) for k in GAUSSIAN_KEYS}
        keep = 1.0 / (1.0 + np.exp(-g["opacity_logits"].astype(np.float64))) >= PRUNE_OPACITY
        counts["pruned"] = int(keep.size - keep.sum())
        gauss = Gaussians(**{k: np.ascontiguousarray(v[keep]) for k, v in g.items()})
        counts["total"] = len(gauss)
        counts["voxels"] = n_vox
        t["gaussians"] = time.perf_counter() - t0
        return gauss, counts

    def camera_details(self, rig: Rig, images: Sequence[np.ndarray], coarse: Gaussians, lidar: np.ndarray | None,
                       opts: DetailOptions, counts: dict[str, int],
                       ego_masks: Mapping[str, np.ndarray] | None = None, lidar_is_sweep: bool = True,
                       threads: int = 1) -> tuple[list[Gaussians], list, list[int]]:
        """Each pinhole camera's detail layer (any lens: on its cells' true rays), not fused: (its Gaussians, its
        runtime.detail.CameraDetail, its index in the rig) per camera. images: the full-resolution inputs in rig
        order (an RgbImages: taken as they are; else each made so by as_rgb); coarse: the model's Gaussians; lidar
        [P, 3] metres, ego frame, or None. Adds to ``counts``:
        detail_lidar / detail_ground / detail_model / detail_far (cells placed by LiDAR, by the ground plane (the
        LiDAR's; camera only, the model's), by the model's depth, at the far depth), detail_edge (cells dropped at
        depth edges). runtime.detail.fuse_details fuses them with ``coarse`` (reconstruct). ego_masks: keyframe's;
        a camera's own ego_mask file wins. lidar_is_sweep=False (``lidar`` is a few hundred stereo points, on walls
        and cars rather than the road: no plane fits them): the ground plane and its trust are the model's, as
        camera only, and the points place only the cells near them (runtime.detail.camera_detail's ``sweep``).
        threads > 1: that many cameras at a time (where numba's threading layer is thread-safe): a camera's detail
        is numba kernels (parallel, the GIL released) between numpy and OpenCV steps on one core, which a second
        camera fills (one PandaSet frame with LiDAR, warm: 2.48 -> 2.08 s; its peak memory holds two cameras'
        full-resolution work, ~0.5 GB more)."""
        from .detail import (
            camera_detail,
            depth_samples,
            fit_ground,
            grid_camera,
            model_ground,
            read_ego_mask,
            rig_depth_scale,
        )

        parts, details, owners = [], [], []
        c = {f"detail_{k}": 0 for k in ("lidar", "ground", "model", "far", "edge")}
        plane = None
        swept = lidar is not None and lidar_is_sweep
        if opts.ground:       # the LiDAR's ground, else (camera only, stereo points) the model's
            plane = fit_ground(lidar) if swept else model_ground(coarse)
        # stereo points: one depth scale for the rig's cameras (rig_depth_scale, from each camera's samples, made
        # once and handed to camera_detail); a sweep: each camera its own
        samples: dict[str, tuple] = {}
        rig_scale = None
        if lidar is not None and not lidar_is_sweep:
            samples = {c.name: depth_samples(grid_camera(c, opts.stride), coarse, lidar, opts)
                       for c in rig.cameras if c.model == "pinhole"}
            rig_scale = rig_depth_scale(list(samples.values()))

        def one(img, cam):
            """A camera's detail: (the camera, camera_detail's Gaussians, CameraDetail, counts)."""
            mask_file = cam.extra.get("ego_mask")
            mask = read_ego_mask(rig.path(mask_file), cam) if mask_file is not None else \
                (ego_masks or {}).get(cam.name)
            rgb = img if isinstance(images, RgbImages) else as_rgb(img, cam)
            return cam, camera_detail(cam, rgb, coarse, opts, lidar, mask, plane,
                                      sweep=swept, depth_scale=rig_scale, samples=samples.get(cam.name))

        todo = [(img, cam) for img, cam in zip(images, rig.cameras) if cam.model == "pinhole"]
        done = in_threads(lambda a: one(*a), todo, threads if threadsafe() else 1)
        for cam, (g, d, n) in done:
            parts.append(g)
            details.append(d)
            owners.append(rig.names.index(cam.name))
            for k, v in n.items():
                c[f"detail_{k}"] += v
        if parts:
            counts.update(c)
        return parts, details, owners

    def lidar_depths(self, rig: Rig, gauss: Gaussians, lidar: np.ndarray, depth: np.ndarray, mask: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, list[float | None]]:
        """The encode graph's depth inputs with LiDAR: for each camera with K (any lens) whose depth is not supplied
        (mask 0), ``runtime.lidar.fuse_depth`` of the sweep's nearest point per depth cell (occlusion-filtered;
        projected through the camera's lens) and the depth of ``gauss`` (the reconstruction without LiDAR) along
        the cells' true rays (runtime.raydepth), both in the camera's depth (Camera.depth_is_distance). lidar: [P, 3]
        metres, ego frame. Returns (depth [N, 1, h, w], depth_mask [N], the scale per camera or None where the
        camera kept its input)."""
        from .lidar import fuse_depth, lidar_depth_map, occlusion_filter
        from .raydepth import render_ray_depth

        pts = np.asarray(lidar, np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
            raise InferenceError("lidar", f"need finite points of shape [P, 3] (got {list(pts.shape)})")
        h, w = self.info.depth_size
        depth, mask = depth.copy(), mask.copy()
        scales: list[float | None] = []
        for n, cam in enumerate(rig.cameras):
            if mask[n] > 0 or cam.model != "pinhole":
                scales.append(None)
                continue
            small = cam.resized(w, h)                        # the lens kept: LiDAR and model along true rays
            lid = lidar_depth_map(pts, small)
            lid = np.where(occlusion_filter(lid, radius=1), lid, 0).astype(np.float32)
            model_depth, model_alpha = render_ray_depth(gauss, small)
            depth[n, 0], s = fuse_depth(lid, model_depth, model_alpha)
            mask[n] = 1.0
            scales.append(s)
        return depth, mask, scales

    # -- background ---------------------------------------------------------------------------------------------
    def background_spec(self, rig: Rig):
        """The cylinder ZNet_bg samples (the volume module's), at the model's H_u x W_u."""
        lift, _ = self.lifting(rig)
        return spec_from_array(lift["spec_vol"], self._params.height, self._params.width)

    def synth_radius(self) -> int:
        """View-space receptive radius of the background synthesis (one pixel per 3x3 modulated conv)."""
        return len(self.info.config["background"]["synth_dims"]) - 1

    def bake_background(self, rig: Rig, app_plane: np.ndarray, scale: int | None = None) -> Background:
        """Run the background graph once with the cylinder itself as the view: a panorama of
        (scale H_u + rows beyond the caps) x scale W_u pixels (docs/inference.md, "Background")."""
        scale = int(scale or self.bake_scale)
        spec = self.background_spec(rig)
        r = self.synth_radius()
        grid, v_range, crop = bake_grid(spec.height * scale, spec.width * scale, margin=2 * r + 2, radius=r)
        img = self._run("background", {"app_plane": app_plane, "grids": grid[None]})["background"][0]
        img = img.transpose(1, 2, 0)[crop]
        return Background(image=np.ascontiguousarray(img, np.float32), cylinder=spec, v_range=v_range)

    def background_network(self, scene: Scene, camera) -> np.ndarray:
        """The background network run per view (the reference the baked panorama approximates): [H, W, 3] for a
        runtime.camera.Camera (pinhole), from the scene's in-memory appearance plane."""
        if scene.app_plane is None or "background" not in self.sessions or scene.background is None:
            raise InferenceError("background", "this scene has no appearance plane (loaded from disk?) or the "
                                               "model no background graph")
        g = background_grid(scene.background.cylinder, camera.K, camera.cam_to_ego, camera.width, camera.height)
        out = self._run("background", {"app_plane": scene.app_plane, "grids": g[None]})["background"][0]
        return np.ascontiguousarray(out.transpose(1, 2, 0))


__all__ = ["MODEL_FORMAT", "InferenceError", "ModelError", "ModelInfo", "Reconstructor", "RgbImages",
           "calibration_key", "default_model_dir", "read_model_file", "read_model_info", "rgb_of", "scene_model_of",
           "select_voxels", "verify_model"]
