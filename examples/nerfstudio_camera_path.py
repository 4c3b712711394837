"""Write a nerfstudio camera_path.json (an orbit or a dolly) and render it on an xyzcyl server.

nerfstudio's camera path format (what its viewer exports and ``ns-render camera-path`` reads): ``render_width``,
``render_height``, ``fps``, ``seconds``, ``camera_type`` and per frame ``camera_to_world`` (16 numbers, row-major,
OpenGL camera axes: x right, y up, z backwards), ``fov`` (VERTICAL degrees) and ``aspect``. The world is the
scene's ego frame (x forward, y left, z up, metres). The server reads the file as it is (POST
/v1/scenes/{id}/render); this script only places the cameras.

- ``--kind orbit``: the camera circles a point ahead of the car (--target) at the distance from the rig, sweeping
  --arc degrees, always looking at it;
- ``--kind dolly``: the camera moves forward along the lane by --distance metres, looking ahead.

Run it against a server (in another shell: ``xyzcyl serve --port 8000``):

    python examples/nerfstudio_camera_path.py --server http://127.0.0.1:8000 --kind orbit --out ns_orbit
    python examples/nerfstudio_camera_path.py --scene SCENE_ID --kind dolly --frames 48 --out ns_dolly

Without --scene it first reconstructs examples/synth_nuscenes/ (or --rig). It writes OUT/camera_path.json (also
usable with nerfstudio), the frames OUT/frame_00000.png ..., OUT/index.json and OUT/path.mp4 (--no-video to skip).
The same file renders with the CLI: ``xyzcyl client path SCENE_ID OUT/camera_path.json --out DIR --video v.mp4``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def look_at_gl(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] camera-to-world with OpenGL camera axes (x right, y up, z backwards: the camera looks along -z)
    for a camera at ``eye`` looking at ``target``, world ``up`` kept upright."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, -forward, eye
    return m


def camera_path(poses: list[np.ndarray], width: int, height: int, vfov: float, fps: float) -> dict:
    """A nerfstudio camera_path.json document."""
    return {"camera_type": "perspective", "render_width": width, "render_height": height, "fps": fps,
            "seconds": len(poses) / fps,
            "camera_path": [{"camera_to_world": p.reshape(-1).tolist(), "fov": vfov, "aspect": width / height}
                            for p in poses]}


def orbit(target, eye_height: float, arc_deg: float, frames: int) -> list[np.ndarray]:
    """Cameras on a horizontal arc around ``target`` through the ego origin's vertical, looking at the target."""
    t = np.asarray(target, dtype=np.float64)
    radius = math.hypot(t[0], t[1])
    base = math.atan2(-t[1], -t[0])                    # the direction from the target back to the rig
    poses = []
    for a in np.radians(np.linspace(-arc_deg / 2, arc_deg / 2, frames)):
        eye = (t[0] + radius * math.cos(base + a), t[1] + radius * math.sin(base + a), eye_height)
        poses.append(look_at_gl(eye, t))
    return poses


def dolly(distance: float, eye_height: float, frames: int, look_ahead: float = 10.0,
          drop: float = 0.4) -> list[np.ndarray]:
    """Cameras moving forward along ego x, looking ``look_ahead`` metres ahead and ``drop`` metres down."""
    return [look_at_gl((x, 0.0, eye_height), (x + look_ahead, 0.0, eye_height - drop))
            for x in np.linspace(0.0, distance, frames)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 epilog="See the module docstring (and docs/client.md) for how to run it.")
    ap.add_argument("--server", default=None, help="base URL (default $XYZCYL_SERVER, else http://127.0.0.1:8000)")
    ap.add_argument("--api-key", default=None, help="API key (default $XYZCYL_API_KEY)")
    ap.add_argument("--scene", default=None, help="a ready scene id (default: reconstruct --rig first)")
    ap.add_argument("--rig", default=str(HERE / "synth_nuscenes" / "rig.json"), help="rig.json to reconstruct")
    ap.add_argument("--kind", choices=("orbit", "dolly"), default="orbit")
    ap.add_argument("--out", default="ns_path", help="output folder")
    ap.add_argument("--frames", type=int, default=36)
    ap.add_argument("--target", type=float, nargs=3, default=(12.0, 0.0, 1.0), metavar=("X", "Y", "Z"),
                    help="orbit: the point looked at, ego frame, metres")
    ap.add_argument("--arc", type=float, default=40.0, help="orbit: degrees swept around the target")
    ap.add_argument("--distance", type=float, default=10.0, help="dolly: metres travelled forward")
    ap.add_argument("--eye-height", type=float, default=1.6, help="camera height, metres")
    ap.add_argument("--vfov", type=float, default=50.0, help="vertical field of view, degrees")
    ap.add_argument("--width", type=int, default=800)
    ap.add_argument("--height", type=int, default=450)
    ap.add_argument("--fps", type=float, default=12.0)
    ap.add_argument("--no-video", action="store_true", help="frames only")
    args = ap.parse_args(argv)

    from xyzcyl.clients import Client, XyzcylError
    from xyzcyl.clients.client import write_video

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    poses = (orbit(args.target, args.eye_height, args.arc, args.frames) if args.kind == "orbit"
             else dolly(args.distance, args.eye_height, args.frames))
    doc = camera_path(poses, args.width, args.height, args.vfov, args.fps)
    path_file = out / "camera_path.json"
    path_file.write_text(json.dumps(doc, indent=1) + "\n")
    try:
        with Client(args.server, api_key=args.api_key, timeout=120.0) as client:
            scene_id = args.scene
            if scene_id is None:
                print(f"reconstructing {args.rig} on {client.base_url} ...", file=sys.stderr)
                scene_id = client.reconstruct(args.rig).id
            with client.render_path(scene_id, path_file, decode=False,
                                    progress=lambda k, n: print(f"\rframe {k}/{n}", end="", file=sys.stderr)
                                    ) as batch:
                print(file=sys.stderr)
                names = batch.save(out)
    except XyzcylError as e:
        print(f"nerfstudio_camera_path: {e}", file=sys.stderr)
        return 2
    print(f"{path_file} and {len(names)} frames in {out}/", file=sys.stderr)
    if not args.no_video:
        video = out / "path.mp4"
        err = write_video(out, names, "rgb", video, args.fps)
        print(f"video: {err or video}", file=sys.stderr)
    print(scene_id)
    return 0


if __name__ == "__main__":
    sys.exit(main())
