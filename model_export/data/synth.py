"""Render synthetic scenes and write the data set (one folder per scene; format in docs/data.md)."""

from __future__ import annotations

import functools
import json
import os
import shutil
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from xyzcyl.common.media import write_exr
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.rig import read_image

from . import classes as C
from .occupancy import PAPER_RANGE, OccupancyGrid, bev, occupancy
from .rigs import K_from_fov, base_rig, ego_forward_targets, inward_directions, jitter, look_at
from .scene import GENERATOR_VERSION, Scene, SceneConfig, sample_scene
from .trace import Grid, View, build_grid, point_inside, render_view, segment_blocked

SETTINGS = ("ego-forward", "ego-inward")


@dataclass(frozen=True)
class SynthConfig:
    """Everything that determines a data set besides the scene count (stored in index.json)."""

    rig: str = "nuscenes"  # preset (rigs.PRESETS) or path to a rig JSON
    height: int = 224  # pixels, every view
    width: int = 400
    targets: tuple[str, ...] = SETTINGS
    inward_views: int = 16  # V, ego-inward cameras per scene
    inward_radius: tuple[float, float] = (8.0, 15.0)  # metres, hemisphere radius range (one radius per scene)
    inward_hfov: float = 70.0  # degrees
    supersample: int = 2  # ss x ss samples per pixel for RGB
    shadows: bool = True
    voxels: tuple[float, ...] = (0.4, 0.8)  # occupancy voxel sizes, metres
    occ_range: tuple[float, ...] = PAPER_RANGE
    jitter_pos_m: float = 0.02
    jitter_deg: float = 0.5
    seed: int = 0
    near_cars: float = 0.0  # probability of traffic beside the ego (SceneConfig.near_cars); 0 = generator v1 as is
    photo_textures: float = 0.0  # probability of a scene with real photo surfaces (SceneConfig.photo_textures); 0 = v1

    def validate(self) -> None:
        """Raise ValueError naming the field."""
        if not (8 <= self.height <= 4096):
            raise ValueError(f"height: must be in 8..4096, got {self.height}")
        if not (8 <= self.width <= 4096):
            raise ValueError(f"width: must be in 8..4096, got {self.width}")
        for t in self.targets:
            if t not in SETTINGS:
                raise ValueError(f"targets: unknown setting {t!r} (choose from {', '.join(SETTINGS)})")
        if not (1 <= self.inward_views <= 1000):
            raise ValueError(f"inward_views: must be in 1..1000, got {self.inward_views}")
        if not (1 <= self.supersample <= 8):
            raise ValueError(f"supersample: must be in 1..8, got {self.supersample}")
        if not (0 < self.inward_radius[0] <= self.inward_radius[1]):
            raise ValueError(f"inward_radius: need 0 < min <= max, got {self.inward_radius}")
        self.scene_config()  # raises naming 'near_cars' or 'photo_textures'
        for v in self.voxels:
            OccupancyGrid(tuple(self.occ_range), float(v))  # raises naming 'voxel'
        base_rig(self.rig, self.width, self.height)  # raises naming 'rig'

    def scene_config(self) -> SceneConfig:
        """The scene sampler's knobs for this data set."""
        return SceneConfig(with_ego="ego-inward" in self.targets, near_cars=self.near_cars,
                           photo_textures=self.photo_textures)

    def to_json(self) -> dict:
        d = asdict(self)
        d["targets"] = list(self.targets)
        d["voxels"] = list(self.voxels)
        d["occ_range"] = list(self.occ_range)
        d["inward_radius"] = list(self.inward_radius)
        return d


@dataclass(eq=False)
class SceneData:
    scene: Scene
    inputs: list[Camera]
    input_views: list[View]
    targets: dict[str, list[Camera]] = field(default_factory=dict)
    target_views: dict[str, list[View]] = field(default_factory=dict)
    occupancy: dict[str, np.ndarray] = field(default_factory=dict)  # tag -> semantic [X,Y,Z] uint8


def inward_cameras(scene: Scene, grid: Grid, cfg: SynthConfig, rng: np.random.Generator) -> list[Camera]:
    """V cameras on a hemisphere around the ego car looking at its centre.

    A candidate is re-drawn (up to 40 times, random direction in the same elevation band) if its centre is
    inside or within 0.3 m of a solid, or if a solid other than the ego car blocks the line of sight to the
    ego centre; after 40 failures the last candidate is kept and marked "occluded": true.
    """
    radius = rng.uniform(*cfg.inward_radius)
    K = K_from_fov(cfg.inward_hfov, cfg.width, cfg.height)
    centre = scene.ego_centre
    out = []
    for i, d in enumerate(inward_directions(cfg.inward_views, rng)):
        ok = False
        for _ in range(40):
            eye = centre + radius * d
            if not point_inside(eye[0], eye[1], eye[2], 0.3, scene.kind, scene.geo) and not segment_blocked(
                    eye, centre, True, scene.kind, scene.geo, scene.ego, grid.meta, grid.start, grid.items,
                    grid.zmax):
                ok = True
                break
            a = rng.uniform(0, 2 * np.pi)
            z = rng.uniform(np.sin(np.radians(8)), np.sin(np.radians(70)))
            d = np.array([np.sqrt(1 - z * z) * np.cos(a), np.sqrt(1 - z * z) * np.sin(a), z])
        out.append(Camera(name=f"inward_{i:03d}", width=cfg.width, height=cfg.height, K=K,
                          cam_to_ego=look_at(eye, centre), extra={"occluded": not ok}))
    return out


def render_scene(cfg: SynthConfig, index: int) -> SceneData:
    """Sample and render scene `index` of the data set (deterministic in (cfg.seed, index))."""
    scene = sample_scene(cfg.seed, index, cfg.scene_config())
    grid = build_grid(scene)
    rng = np.random.default_rng([int(cfg.seed), int(index), 0xCA3])
    cams = jitter(base_rig(cfg.rig, cfg.width, cfg.height), rng, cfg.jitter_pos_m, cfg.jitter_deg)

    def draw(cs: list[Camera], skip_ego: bool) -> list[View]:
        return [render_view(scene, grid, c, cfg.supersample, skip_ego, cfg.shadows) for c in cs]

    data = SceneData(scene, cams, draw(cams, True))
    for setting in cfg.targets:
        if setting == "ego-forward":
            tc = ego_forward_targets(cams, scene.lane_dir, rng)
            data.targets[setting], data.target_views[setting] = tc, draw(tc, True)
        else:
            tc = inward_cameras(scene, grid, cfg, rng)
            data.targets[setting], data.target_views[setting] = tc, draw(tc, False)
    for v in cfg.voxels:
        g = OccupancyGrid(tuple(cfg.occ_range), float(v))
        data.occupancy[g.tag] = occupancy(scene, g)
    return data


# --------------------------------------------------------------------------------------------------------------
# files


def read_exr(path: Path) -> np.ndarray:
    """[H, W] float32 depth from a single-channel EXR written by _write_views (runtime.imageio.write_exr)."""
    return read_image(path, "depth", channels=1, scale=False)[..., 0]


def _write_png(path: Path, img: np.ndarray) -> None:
    import cv2

    if img.ndim == 3:
        img = img[..., ::-1]
    if not cv2.imwrite(str(path), np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise OSError(f"cannot write {path}")


def _write_views(folder: Path, sub: str, cams: list[Camera], views: list[View]) -> list[dict]:
    (folder / sub).mkdir(parents=True, exist_ok=True)
    out = []
    for c, v in zip(cams, views):
        files = {"image": f"{sub}/{c.name}.png", "depth": f"{sub}/{c.name}_depth.exr",
                 "sky": f"{sub}/{c.name}_sky.png", "semantic": f"{sub}/{c.name}_sem.png"}
        _write_png(folder / files["image"], v.rgb)
        write_exr(folder / files["depth"], v.depth[..., None], ("Z",), compression="zip")   # lossless
        _write_png(folder / files["sky"], (v.sky * 255).astype(np.uint8))
        _write_png(folder / files["semantic"], v.semantic)
        d = c.replace(image=files["image"], depth=files["depth"]).to_dict()
        d["sky"], d["semantic"] = files["sky"], files["semantic"]
        out.append(d)
    return out


FRAME = "ego: x forward, y left, z up (metres); origin = rear axle centre on the ground (z = 0)"


def write_scene(data: SceneData, folder: Path, cfg: SynthConfig) -> None:
    """Write one scene into `folder` (created; must not exist)."""
    folder.mkdir(parents=True)
    src = f"xyzcyl synthetic v{GENERATOR_VERSION} seed {cfg.seed} scene {data.scene.index}"
    rig = {"source": src, "license": "generated (CC0)", "frame": FRAME, "generator_version": GENERATOR_VERSION,
           "seed": cfg.seed, "scene_index": data.scene.index, "depth_sky_value": 0.0,
           "cameras": _write_views(folder, "inputs", data.inputs, data.input_views)}
    (folder / "rig.json").write_text(json.dumps(rig, indent=1) + "\n")
    targets = {"source": src, "frame": FRAME, "settings": {}}
    for setting, cams in data.targets.items():
        targets["settings"][setting] = {
            "frame": FRAME, "cameras": _write_views(folder, f"targets/{setting}", cams, data.target_views[setting])}
    (folder / "targets.json").write_text(json.dumps(targets, indent=1) + "\n")
    occ = {"range": np.asarray(cfg.occ_range, np.float32)}
    for tag, sem in data.occupancy.items():
        occ[f"semantic_{tag}"] = sem
        occ[f"occupied_{tag}"] = sem > 0
        occ[f"bev_{tag}"] = bev(sem)
    np.savez_compressed(folder / "occupancy.npz", **occ)
    np.savez_compressed(folder / "scene.npz", **data.scene.arrays())


def scene_name(index: int) -> str:
    return f"scene_{index:06d}"


def index_doc(cfg: SynthConfig, n: int) -> dict:
    return {"generator": "xyzcyl.model_export.data", "generator_version": GENERATOR_VERSION, "seed": cfg.seed,
            "scenes": n, "config": cfg.to_json(),
            "classes": {str(k): v[0] for k, v in C.CLASSES.items()}, "scene_folders": "scene_{index:06d}"}


def _write_atomic(data: SceneData, out: Path, cfg: SynthConfig) -> None:
    """Write the scene into out/.tmp/<name> (replacing a leftover partial folder), then rename it to out/<name>."""
    name = scene_name(data.scene.index)
    part = out / ".tmp" / name
    if part.exists():
        shutil.rmtree(part)
    write_scene(data, part, cfg)
    os.replace(part, out / name)


def cores() -> int:
    """CPU cores this process may use (its affinity mask), at most numba's pool size (NUMBA_NUM_THREADS)."""
    import numba

    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(n, numba.config.NUMBA_NUM_THREADS))


def _worker_init(threads: int) -> None:
    """Pool worker set-up: `threads` numba threads (workers x threads <= cores); OpenImageIO's pool likewise."""
    import numba

    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        import OpenImageIO as oiio

        oiio.attribute("threads", threads)
        oiio.attribute("exr_threads", threads)
    except ImportError:  # write_exr reports the missing module itself
        pass


def _render_and_write(cfg: SynthConfig, index: int, out: Path) -> int:
    _write_atomic(render_scene(cfg, index), out, cfg)
    return index


def open_output(out: str | Path, workers: int, cfg) -> Path:
    """The output folder (made) of a generator run with ``cfg`` (its validate() raises for a bad config) and
    ``workers`` (ValueError unless an integer >= 1): synth and the synthetic drive (drive.py)."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers: must be an integer >= 1, got {workers!r}")
    cfg.validate()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return out


def produce(todo: list[int], workers: int, render, write, task, done) -> None:
    """Render and write each item of ``todo``: with one worker in this process (``render(i)`` -> data, then
    ``write(data)`` in a thread while the next item renders), else in ``workers`` spawned processes each running
    ``task(i)`` (picklable: render and write one item) with its share of the cores. ``done()`` after each item is
    written. synth and the synthetic drive (drive.py) both write so."""
    if workers <= 1:
        pending: Future | None = None
        with ThreadPoolExecutor(1) as pool:
            for i in todo:
                data = render(i)
                if pending is not None:
                    pending.result()
                    done()
                pending = pool.submit(write, data)
            if pending is not None:
                pending.result()
                done()
        return
    # spawn, not fork: numba's omp threading layer (GNU OpenMP) is not fork-safe once its pool has started
    import multiprocessing

    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_worker_init, initargs=(max(1, cores() // workers),))
    try:
        for f in as_completed([pool.submit(task, i) for i in todo]):
            f.result()
            done()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def synth(out: Path, n: int, cfg: SynthConfig, progress: bool = True, workers: int = 1) -> int:
    """Render scenes 0..n-1 into `out`, skipping finished ones; returns the number rendered now.

    Each scene is written into a temporary folder and renamed into place, so a folder named scene_XXXXXX is
    always complete. An existing index.json must have the same config (ValueError naming the field).

    workers 1: one process; numba renders each scene on all its threads while a background thread writes the
    previous one. workers N > 1: N spawned processes render and write whole scenes side by side, each with
    max(1, cores() // N) numba threads. The files are the same byte for byte whatever `workers` is.
    """
    from xyzcyl.common.progress import progress_bar

    out = open_output(out, workers, cfg)
    idx_path = out / "index.json"
    if idx_path.exists():
        old = json.loads(idx_path.read_text())
        defaults = SynthConfig().to_json()  # a field added later is absent from older index.json: its default
        for k, v in cfg.to_json().items():
            was = old.get("config", {}).get(k, defaults[k])
            if was != v:
                raise ValueError(f"{k}: {out} was made with {k}={was!r}, not {v!r}")
        n_total = max(n, int(old.get("scenes", 0)))
    else:
        n_total = n
    idx_path.write_text(json.dumps(index_doc(cfg, n_total), indent=1) + "\n")  # before any scene: fixes the config
    tmp = out / ".tmp"
    tmp.mkdir(exist_ok=True)
    todo = [i for i in range(n) if not (out / scene_name(i)).is_dir()]
    workers = min(workers, len(todo))
    with progress_bar(total=len(todo), desc="synth", unit="scene", enabled=progress) as bar:
        produce(todo, workers, lambda i: render_scene(cfg, i), lambda data: _write_atomic(data, out, cfg),
                functools.partial(_render_and_write, cfg, out=out), bar.update)
    idx_path.write_text(json.dumps(index_doc(cfg, n_total), indent=1) + "\n")
    shutil.rmtree(tmp, ignore_errors=True)
    return len(todo)
