"""A CARLA-style camera sensor driving along the lane through a reconstructed scene: frames and an mp4 video.

The sensor is described exactly as a CARLA camera blueprint is (a transform relative to the vehicle, in CARLA's
left-handed axes: x forward, y right, z up, metres; pitch/yaw/roll in degrees; ``fov`` horizontal degrees;
``image_size_x`` x ``image_size_y``). The server converts it (runtime.convert.camera_from_carla); this script only
moves the sensor forward from x = 0 to x = 20 m and asks for one batch of views (POST /v1/scenes/{id}/render).

Run it against a server (in another shell: ``xyzcyl serve --port 8000``):

    python examples/carla_trajectory.py --server http://127.0.0.1:8000 --out carla_drive
    python examples/carla_trajectory.py --scene SCENE_ID --frames 81 --y -1.5 --yaw -10 --out carla_drive

Without --scene it first reconstructs examples/synth_nuscenes/ (or --rig) on the server. It writes
OUT/frame_00000.png ... (the server's PNGs as they are), OUT/index.json (each frame's K and cam_to_ego in the ego
frame) and OUT/drive.mp4 (OpenCV, mp4v; --no-video to skip). --server and --api-key default to $XYZCYL_SERVER and
$XYZCYL_API_KEY.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def carla_sensor(x: float, y: float, z: float, pitch: float, yaw: float, roll: float, fov: float, width: int,
                 height: int) -> dict:
    """A CARLA camera sensor (sensor.camera.rgb) as its blueprint attributes and transform."""
    return {"transform": {"location": {"x": x, "y": y, "z": z}, "rotation": {"pitch": pitch, "yaw": yaw, "roll": roll}},
            "fov": fov, "image_size_x": width, "image_size_y": height}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 epilog="See the module docstring (and docs/client.md) for how to run it.")
    ap.add_argument("--server", default=None, help="base URL (default $XYZCYL_SERVER, else http://127.0.0.1:8000)")
    ap.add_argument("--api-key", default=None, help="API key (default $XYZCYL_API_KEY)")
    ap.add_argument("--scene", default=None, help="a ready scene id (default: reconstruct --rig first)")
    ap.add_argument("--rig", default=str(HERE / "synth_nuscenes" / "rig.json"), help="rig.json to reconstruct")
    ap.add_argument("--out", default="carla_drive", help="output folder (frames, index.json, drive.mp4)")
    ap.add_argument("--frames", type=int, default=41, help="number of frames (default 41: every 0.5 m)")
    ap.add_argument("--x-start", type=float, default=0.0, help="first sensor x, metres (CARLA: forward)")
    ap.add_argument("--x-end", type=float, default=20.0, help="last sensor x, metres")
    ap.add_argument("--y", type=float, default=0.0, help="lateral offset, metres (CARLA: + right)")
    ap.add_argument("--z", type=float, default=1.6, help="sensor height above the ego origin, metres")
    ap.add_argument("--pitch", type=float, default=0.0, help="degrees (+ up)")
    ap.add_argument("--yaw", type=float, default=0.0, help="degrees (+ right)")
    ap.add_argument("--fov", type=float, default=90.0, help="horizontal field of view, degrees")
    ap.add_argument("--width", type=int, default=800)
    ap.add_argument("--height", type=int, default=450)
    ap.add_argument("--fps", type=float, default=10.0, help="video frame rate")
    ap.add_argument("--no-video", action="store_true", help="frames only")
    args = ap.parse_args(argv)

    from xyzcyl.clients import Client, XyzcylError
    from xyzcyl.clients.client import write_video

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        with Client(args.server, api_key=args.api_key, timeout=120.0) as client:
            scene_id = args.scene
            if scene_id is None:
                print(f"reconstructing {args.rig} on {client.base_url} ...", file=sys.stderr)
                scene = client.reconstruct(args.rig)
                scene_id = scene.id
                print(f"scene {scene_id}: {scene.gaussians} Gaussians", file=sys.stderr)
            xs = np.linspace(args.x_start, args.x_end, args.frames)
            sensors = [carla_sensor(float(x), args.y, args.z, args.pitch, args.yaw, 0.0, args.fov, args.width,
                                    args.height) for x in xs]
            with client.render_path(scene_id, {"cameras": sensors}, decode=False,
                                    progress=lambda k, n: print(f"\rframe {k}/{n}", end="", file=sys.stderr)
                                    ) as batch:
                print(file=sys.stderr)
                names = batch.save(out)
    except XyzcylError as e:
        print(f"carla_trajectory: {e}", file=sys.stderr)
        return 2
    print(f"{len(names)} frames in {out}/ (x = {args.x_start:g} .. {args.x_end:g} m)", file=sys.stderr)
    if not args.no_video:
        video = out / "drive.mp4"
        err = write_video(out, names, "rgb", video, args.fps)
        print(f"video: {err or video}", file=sys.stderr)
    print(scene_id)
    return 0


if __name__ == "__main__":
    sys.exit(main())
