"""The ego's own body found over a drive's frames: the pixels of a camera that stay put while the world moves.

Hood, mirrors, trunk and roof move with the cameras. In one frame nothing tells them from the road; over a drive
they are the pixels whose colour does not change although the ego moved far enough that a world-fixed surface
there would have moved across the image. find_ego_body, per camera (docs/inference.md "The ego's own body"):

1. frames: up to FRAMES frames of the drive spread evenly over the distance the ego travelled (a still stretch
   counts once); under MIN_TRAVEL_M travelled nothing is decidable and no camera gets a mask;
2. each frame's image at ANALYSIS_WIDTH pixels, divided by its own median colour (auto exposure and white
   balance change between frames; the body's colour follows the same gain), blurred 3x3 (JPEG noise);
3. a pixel is still when its change (the STILL_RANK-th fraction of the frames' mean absolute difference to the
   pixel's median over frames) is under STILL_LEVEL of the median colour;
4. a pixel is decidable when a world-fixed point on its ray (on the ground where the ray meets it within
   FAR_M, else at infinity: only rotation moves it) would move at least MIN_SHIFT_PX analysis pixels between the
   first and the last chosen frame (the first's point in the last's image, or where that leaves the view, the
   last's point in the first's). The sky and a distant skyline stay put too: they are not decidable;
5. stillness is evidence only where the surface is textured along that motion (texture_change >= TEXTURE_LEVEL:
   uniform asphalt or paint stays the same colour when it moves): a textured, decidable pixel is body evidence
   when still, world evidence when it changed; with LiDAR, a return farther than BODY_RANGE_M from the camera is
   world evidence too;
6. the body's outline is body evidence in connected runs spanning at least OUTLINE_SPAN of the image width; each
   column is walked up from the image's bottom edge while it meets no world evidence and stays decidable, and the
   body there reaches the highest outline pixel met. Columns beside found ones whose outline went unseen take
   their neighbour's height where their own run allows it (RUN_REACH, RUN_STILL); the height profile is smoothed
   (median of 5, closing of PROFILE_CLOSE). Under MIN_AREA of the image, nothing is found. The mask is grown by
   GROW_FRAC of the image width (its edge pixels blend the body and the world);
7. a camera whose textured pixels barely changed (under MIN_CHANGED of them) or whose body would cover more than
   MAX_AREA of its image is reported frozen and gets no mask: its images did not change while the ego moved (a
   stuck camera, or one image posted for every frame).

Only bodies along the image's bottom edge are searched: hoods, trunks, a roof seen by a downward camera. Mirrors
at the image's sides are not (their rays look sideways at the horizon, where stillness says little). A car
followed at the same distance for the whole drive is world evidence only where LiDAR sees it; without LiDAR its
outline is not long enough to be taken (OUTLINE_SPAN) unless it fills a quarter of the image's width.

The ground for step 4 is the first LiDAR sweep's ground (runtime.detail.fit_ground) where the drive has one, else
the ego frame's z = 0 (nuScenes' and PandaSet's ego frames sit on the ground).

A rig camera's own ``ego_mask`` always wins: such a camera is not searched. What is found is used exactly as a
given ego_mask (no detail cells there) and saved with the scene (runtime.scene: ``ego_body/<camera>.png``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from .camera import Camera

FRAMES = 10                 # frames looked at: enough for a robust median, 60 decodes for a 6-camera rig
MIN_TRAVEL_M = 1.5          # under this the road a few metres away moves too little to tell from the body
ANALYSIS_WIDTH = 320        # pixels: the body is large (a hood or trunk spans >5 % of the image)
STILL_RANK = 0.75           # a pixel that changes in a quarter of the frames (a passing car) still changed
STILL_LEVEL = 0.035         # of the median colour: above JPEG noise on a blurred analysis pixel (~1 %), below the
#                             change of textured road shifted by a few pixels (PandaSet: 0.1-0.3)
MIN_SHIFT_PX = 4.0          # analysis pixels a world point must move for stillness to say "body"
FAR_M = 200.0               # a downward ray meeting the ground beyond this is treated as meeting the horizon
MIN_AREA = 0.005            # of the image: smaller still regions are texture-less road or noise, not a body
MAX_AREA = 0.45             # of the image: a larger "body" is a camera whose images did not change
MIN_CHANGED = 0.2           # of the textured pixels that should have moved: fewer changed, the camera is frozen
#                             (PandaSet's cameras over 2.6 m: 0.5-0.9; the back camera with its trunk the least)
GROW_FRAC = 0.006           # of the image width: the body's edge (PandaSet's 1920 px: 12 px)
FLOW_CAP_PX = 6.0           # analysis pixels: texture_change looks this far along the world's motion
TEXTURE_LEVEL = 0.1         # of the median colour: a surface whose shift changes it this much is textured (an
#                             edge or a marking); below, stillness is no evidence either way
OUTLINE_SPAN = 0.25         # of the image width: a body's outline is one long connected run of still texture
RUN_STILL = 0.6             # a column taken from its neighbour: this share of its run must be still
PROFILE_CLOSE = 15          # analysis pixels: the body's top edge is smooth; narrower notches are closed
RUN_REACH = 0.7             # ... and it must reach this share of the neighbour's height (a curved edge)
BODY_RANGE_M = 5.0          # a LiDAR return farther than this from the camera is the world (the body is closer)
EGO_THREADS = 2             # frames read at once (two cores: a frame's decoding beside another's resizing)


@dataclass(frozen=True)
class EgoBody:
    """What find_ego_body found. masks: camera name -> [H, W] bool at the camera's full size, True = the ego's
    body; fractions: camera name -> the share of the image masked (every searched camera, 0 when none);
    notes: camera name -> why it has no mask (frozen) where that is not simply "nothing found"; frames: the drive
    frames looked at; travelled_m: the ego's distance over the drive (metres)."""
    masks: dict[str, np.ndarray] = field(default_factory=dict)
    fractions: dict[str, float] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)
    frames: tuple[int, ...] = ()
    travelled_m: float = 0.0

    def summary(self) -> dict:
        """The JSON-ready record scene.json keeps (without the masks)."""
        return {"frames": list(self.frames), "travelled_m": round(self.travelled_m, 3),
                "fractions": {k: round(v, 4) for k, v in self.fractions.items()}, "notes": dict(self.notes)}


def spread_frames(positions: np.ndarray, count: int = FRAMES) -> tuple[list[int], float]:
    """Up to ``count`` frame indices spread evenly over the distance travelled, and that distance (metres).
    positions: [F, 3] metres, the ego's position per frame in one frame (the scene's). A still stretch gives one
    frame: frames are picked by arc length, the first at each target distance."""
    p = np.asarray(positions, np.float64)
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1) if len(p) > 1 else np.zeros(0)
    s = np.concatenate([[0.0], np.cumsum(steps)])
    total = float(s[-1])
    if total <= 0.0:
        return [0], 0.0
    picks = sorted({int(np.searchsorted(s, t, side="left")) for t in np.linspace(0.0, total, count)})
    return [min(i, len(p) - 1) for i in picks], total


def still_change(images: Sequence[np.ndarray]) -> np.ndarray:
    """[h, w] float: each pixel's change over ``images`` ([h, w, 3] float, one per frame, same camera and size):
    the STILL_RANK quantile over frames of the mean absolute difference (over channels) between the frame,
    divided by its own median colour, and the per-pixel median of those frames; 3x3-blurred inputs."""
    import cv2

    norm = []
    for img in images:
        a = cv2.GaussianBlur(np.asarray(img, np.float32), (3, 3), 0)
        med = np.median(a.reshape(-1, a.shape[-1]), axis=0)
        norm.append(a / np.maximum(med, 1e-3))
    stack = np.stack(norm)                                   # [T, h, w, 3]
    ref = np.median(stack, axis=0)
    diff = np.abs(stack - ref).mean(axis=-1)                 # [T, h, w]
    return np.quantile(diff, STILL_RANK, axis=0)


def world_flow(cam: Camera, first: np.ndarray, last: np.ndarray, ground_z: float) -> np.ndarray:
    """[h, w, 2] float: where (pixels of ``cam``, du dv) a world-fixed point on each pixel's ray in the ``first``
    frame moves in the ``last`` frame's image; NaN where it leaves the view or the pixel has no ray. The point:
    where the ray meets the ground z = ``ground_z`` (ego frame, metres) within FAR_M, else at infinity (moved by
    rotation only: the sky and a distant skyline). first, last: [4, 4] ego -> scene poses of the two frames."""
    o, d = cam.pixel_rays()                                   # [h, w, 3] ego frame of the first frame
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ground_z - o[..., 2]) / d[..., 2]
    hits = np.isfinite(t) & (t > 0) & (t <= FAR_M)
    rel = np.linalg.inv(last) @ first                         # first ego -> last ego
    R, tr = rel[:3, :3], rel[:3, 3]
    p_near = (o + d * np.where(hits, t, 0.0)[..., None]) @ R.T + tr
    q_far = cam.position + d @ R.T * 1e6                       # a direction: translation does not move it
    uv, _, front = cam.project(np.where(hits[..., None], p_near, q_far))
    vv, uu = np.meshgrid(np.arange(cam.height), np.arange(cam.width), indexing="ij")
    flow = np.stack([uv[..., 0] - uu, uv[..., 1] - vv], axis=-1)
    ok = front & cam.inside(uv) & np.all(np.isfinite(d), axis=-1)
    return np.where(ok[..., None], flow, np.nan)


def texture_change(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """[h, w] float: how much a pixel's colour would change if the surface there moved along ``flow`` ([h, w, 2]
    pixels; capped at FLOW_CAP_PX: texture is local): the mean absolute difference (over channels) between
    ``image`` ([h, w, 3], divided by its median colour) and itself sampled FLOW_CAP_PX back along the flow. A
    uniform surface (asphalt, a painted hood) scores ~0: its stillness says nothing."""
    import cv2

    a = np.asarray(image, np.float32)
    a = a / np.maximum(np.median(a.reshape(-1, a.shape[-1]), axis=0), 1e-3)
    f = np.nan_to_num(flow)
    n = np.hypot(f[..., 0], f[..., 1])
    s = np.minimum(n, FLOW_CAP_PX) / np.maximum(n, 1e-6)
    vv, uu = np.meshgrid(np.arange(a.shape[0]), np.arange(a.shape[1]), indexing="ij")
    mx = (uu - f[..., 0] * s).astype(np.float32)
    my = (vv - f[..., 1] * s).astype(np.float32)
    back = cv2.remap(a, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return np.abs(back - a).mean(axis=-1)


def body_mask(change: np.ndarray, texture: np.ndarray, shift: np.ndarray,
              far_returns: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """[h, w] bool: the ego's body at the analysis size along the image's bottom edge (steps 3-6 of the module
    docstring, without the growth); all False when nothing is found. change: still_change; texture:
    texture_change of the median frame; shift: the world flow's length (NaN: no ray); far_returns [h, w] bool or
    None: pixels where a LiDAR return farther than BODY_RANGE_M from the camera landed (the world, not the body).
    Also returns the share of the textured, decidable pixels that changed (near 0: the camera's images did not
    change although the ego moved; find_ego_body calls it frozen)."""
    import cv2

    h, w = change.shape
    decidable = np.nan_to_num(shift) >= MIN_SHIFT_PX
    still = change < STILL_LEVEL
    evidence = decidable & (texture >= TEXTURE_LEVEL)
    body_ev, world_ev = evidence & still, evidence & ~still
    changed = float(world_ev.sum() / max(1, evidence.sum()))
    if far_returns is not None:
        world_ev |= far_returns
    # the outline: body evidence in long connected runs (a hood's or trunk's edge spans much of the image; a car
    # followed at constant distance, or a patch that happened not to change, does not)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(
        cv2.dilate(body_ev.astype(np.uint8), np.ones((3, 3), np.uint8)), connectivity=8)
    long_ = np.zeros(n, bool)
    long_[1:] = stats[1:, cv2.CC_STAT_WIDTH] >= OUTLINE_SPAN * w
    outline = body_ev & long_[labels]
    # walk up each column from the bottom edge while the world shows no sign of itself
    blocked = world_ev | ~decidable
    reach = np.cumsum(blocked[::-1], axis=0)[::-1] == 0        # no blocked pixel between it and the bottom edge
    rows = np.arange(h)[:, None]
    top = np.where(outline & reach, h - rows, 0).max(axis=0)   # [w] the body's height per column
    # columns beside found ones whose own outline went unseen (the body's edge against a same-coloured
    # background): the neighbour's height, or as far as the world lets the column reach when that is nearly it,
    # where the run is mostly still
    reach_h = reach.sum(axis=0)
    for step in (1, -1):
        for u in (range(1, w) if step == 1 else range(w - 2, -1, -1)):
            nb = top[u - step]
            if top[u] == 0 and nb > 0:
                hgt = min(nb, reach_h[u])
                if hgt >= RUN_REACH * nb and still[h - hgt:, u].mean() >= RUN_STILL:
                    top[u] = hgt
    win = np.lib.stride_tricks.sliding_window_view
    top = np.median(win(np.pad(top, 2, mode="edge"), 5), axis=1)                 # lone spikes and notches
    k = PROFILE_CLOSE // 2                                                      # notches up to PROFILE_CLOSE wide
    top = win(np.pad(win(np.pad(top, k, mode="edge"), 2 * k + 1).max(axis=1), k, mode="edge"), 2 * k + 1).min(axis=1)
    out = (h - rows) <= top[None, :]
    if out.sum() < MIN_AREA * h * w:
        return np.zeros((h, w), bool), changed
    return out, changed


def find_ego_body(cameras: Sequence[Camera], images_of, positions: np.ndarray, poses: Sequence[np.ndarray],
                  ground_z: float = 0.0, skip: Sequence[str] = (), lidar_of=None) -> EgoBody:
    """The ego's own body per camera over a drive (module docstring). cameras: the rig's cameras (every frame has
    the same); images_of(i) -> frame i's images ([H, W, 3] float 0..1, rig order); positions [F, 3] metres and
    poses [F] [4, 4] ego -> scene of every frame; ground_z: the ground's height in the ego frame (metres);
    skip: camera names not searched (their rig gives an ego_mask); lidar_of(i) -> frame i's LiDAR points [P, 3]
    metres, ego frame, or None."""
    import cv2

    frames, travelled = spread_frames(positions)
    searched = [i for i, c in enumerate(cameras) if c.name not in set(skip) and c.model == "pinhole"]
    if travelled < MIN_TRAVEL_M or len(frames) < 3 or not searched:
        return EgoBody(frames=tuple(frames), travelled_m=travelled)
    small: dict[int, list[np.ndarray]] = {i: [] for i in searched}
    grids = {i: cameras[i].resized(ANALYSIS_WIDTH, max(1, round(cameras[i].height * ANALYSIS_WIDTH
                                                                 / cameras[i].width))) for i in searched}
    far = {i: np.zeros((g.height, g.width), bool) for i, g in grids.items()}

    def shrunk(f: int) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """Frame f's images at the analysis size and the pixels [P, 2] (column, row) where its LiDAR saw beyond
        BODY_RANGE_M, per searched camera."""
        imgs = images_of(f)
        pts = lidar_of(f) if lidar_of is not None else None
        out, hits = {}, {}
        for i in searched:
            g = grids[i]
            out[i] = cv2.resize(np.asarray(imgs[i], np.float32), (g.width, g.height), interpolation=cv2.INTER_AREA)
            if pts is not None and len(pts):
                uv, _, front = g.project(pts)
                ok = front & g.inside(uv) & (np.linalg.norm(pts - g.position, axis=1) > BODY_RANGE_M)
                hits[i] = np.clip(np.rint(uv[ok]).astype(int), 0, [g.width - 1, g.height - 1])
        return out, hits

    # two frames at a time: decoding and resizing release the GIL (the drive's keyframes wait for these masks);
    # map keeps the frames in order
    with ThreadPoolExecutor(EGO_THREADS) as pool:
        for out, hits in pool.map(shrunk, frames):
            for i in searched:
                small[i].append(out[i])
                if i in hits:
                    far[i][hits[i][:, 1], hits[i][:, 0]] = True
    masks, fractions, notes = {}, {}, {}
    for i in searched:
        c, g = cameras[i], grids[i]
        a, b = np.asarray(poses[frames[0]]), np.asarray(poses[frames[-1]])
        flow = world_flow(g, a, b, ground_z)
        # where the first frame's point leaves the last frame's view (the ground under a front camera's hood passes
        # under the car), the last frame's point seen from the first
        back = world_flow(g, b, a, ground_z)
        flow = np.where(np.isnan(flow[..., :1]), back, flow)
        median = np.median(np.stack(small[i]), axis=0)
        m, changed = body_mask(still_change(small[i]), texture_change(median, flow),
                               np.hypot(flow[..., 0], flow[..., 1]), far[i] if lidar_of is not None else None)
        frac = float(m.mean())
        fractions[c.name] = 0.0
        if changed < MIN_CHANGED or frac > MAX_AREA:
            notes[c.name] = (f"frozen: {1 - changed:.0%} of its textured pixels did not change while the ego moved "
                             f"{travelled:.1f} m; no mask")
            continue
        if not m.any():
            continue
        full = cv2.resize(m.astype(np.float32), (c.width, c.height), interpolation=cv2.INTER_LINEAR) >= 0.5
        r = max(1, math.ceil(GROW_FRAC * c.width))
        full = cv2.dilate(full.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)) > 0
        masks[c.name] = full
        fractions[c.name] = float(full.mean())
    return EgoBody(masks=masks, fractions=fractions, notes=notes, frames=tuple(frames), travelled_m=travelled)


__all__ = ["EgoBody", "body_mask", "find_ego_body", "spread_frames", "still_change", "texture_change", "world_flow"]
