"""Render one camera of a scene through xyzcyl's gRPC SensorsimService, placing it as NVIDIA AlpaSim does
(docs/simulators.md "A client in five lines").

AlpaSim places a camera from two poses: the ego's (its rig frame -> the scene's local frame, from its own trajectory
data at the frame's time) and the camera's mount from ``get_available_cameras`` (the field ``rig_to_camera``, which
holds camera -> rig despite its name: the protocol's own comment says so). The request's sensor pose is their
product (AlpaSim's runtime: ``sensor_pose = ego_pose @ rig_to_camera``):

    sensor_pose = ego_to_world @ rig_to_camera     # [4, 4] camera -> local frame, metres, OpenCV camera axes

Sending ``rig_to_camera`` alone as the sensor pose places the camera as if the ego stood at the local frame's origin
facing its +x: on a scene posted with an ``ego_to_world`` the view is then turned by that pose's yaw (44.7 degrees
on the PandaSet rig of ../shared/data/real) and shifted by its translation. This client takes the ego pose where
xyzcyl keeps it, the top-level ``ego_to_world`` (or ``ego_to_global``) of the rig.json the scene was posted with
(--rig; without it: identity, right for a scene posted without one). With the ego at that recorded pose the image
is the rig camera's own view (the HTTP ``GET /v1/scenes/{id}/render?camera=NAME``, to float32 round-off).

    xyzcyl serve --grpc-port 50051 &            # then post the scene with ?name=SCENE (docs/simulators.md)
    python examples/grpc_client.py --address 127.0.0.1:50051 --scene SCENE --camera CAM_FRONT \\
        --rig examples/synth_nuscenes/rig.json --out front.png

Needs the server extra (grpcio, protobuf): the message classes are xyzcyl's (server/sensorsim/*_pb2.py).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np


def ego_pose(rig_json: str | Path | None) -> np.ndarray:
    """[4, 4] float64 ego -> local frame of the scene: the rig.json's ``ego_to_world`` / ``ego_to_global``, checked
    as the server checks it at the upload (a rigid transform); identity without a rig.json or without either key."""
    if rig_json is None:
        return np.eye(4)
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.server.sensorsim.frames import scene_ego_to_world

    return scene_ego_to_world(load_rig(rig_json, check_images=False))


def render(stub, scene: str, camera: str, ego_to_world: np.ndarray, width: int = 0, height: int = 0,
           metadata: Sequence[tuple[str, str]] = (), timeout: float = 60.0) -> bytes:
    """The PNG of camera ``camera`` (a logical id of get_available_cameras) of ``scene`` (a scene name or id) with
    the ego at ``ego_to_world`` ([4, 4] ego -> local frame), ``width`` x ``height`` pixels (0: the camera's native
    size). ``stub``: a SensorsimServiceStub. LookupError naming --camera when the scene has no such camera."""
    from xyzcyl.server.sensorsim import frames
    from xyzcyl.server.sensorsim import sensorsim_pb2 as pb

    # the five lines of docs/simulators.md "A client in five lines" (with the size asked, the metadata, a check)
    cams = stub.get_available_cameras(pb.AvailableCamerasRequest(scene_id=scene), metadata=metadata,
                                      timeout=timeout).available_cameras
    cam = next((c for c in cams if c.logical_id == camera), None)
    if cam is None:
        raise LookupError(f"--camera: no camera {camera!r} in scene {scene!r} "
                          f"(it has {', '.join(c.logical_id for c in cams) or 'none'})")
    # camera -> local frame = (ego -> local frame) @ (camera -> rig: the field rig_to_camera, despite its name)
    pose = frames.pose_message(np.asarray(ego_to_world, np.float64)
                               @ frames.pose_matrix(cam.rig_to_camera, "rig_to_camera"))
    req = pb.RGBRenderRequest(scene_id=scene, camera_intrinsics=cam.intrinsics, image_format=pb.PNG,
                              sensor_pose=pb.PosePair(start_pose=pose, end_pose=pose), resolution_w=width,
                              resolution_h=height)
    return stub.render_rgb(req, metadata=metadata, timeout=timeout).image_bytes


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--address", default="127.0.0.1:50051",
                    help="the gRPC port, host:port (xyzcyl serve --grpc-port)")
    ap.add_argument("--scene", required=True, help="the scene's name (POST /v1/scenes?name=) or id")
    ap.add_argument("--camera", required=True, help="a camera's logical id (its name in the rig)")
    ap.add_argument("--out", required=True, type=Path, help="the PNG to write")
    ap.add_argument("--rig", help="the rig.json the scene was posted with: its ego_to_world places the ego")
    ap.add_argument("--width", type=int, default=0, help="image width in pixels (0: the camera's)")
    ap.add_argument("--height", type=int, default=0, help="image height in pixels (0: follows the width)")
    ap.add_argument("--api-key", help="sent as x-api-key (servers with api_keys set)")
    args = ap.parse_args(argv)

    import grpc
    from xyzcyl.common.errors import FieldError
    from xyzcyl.server.sensorsim.sensorsim_pb2_grpc import SensorsimServiceStub

    metadata = (("x-api-key", args.api_key),) if args.api_key else ()
    try:
        E = ego_pose(args.rig)
        with grpc.insecure_channel(args.address) as channel:
            png = render(SensorsimServiceStub(channel), args.scene, args.camera, E, args.width, args.height,
                         metadata)
    except (FieldError, LookupError) as e:
        print(f"grpc_client: {e}", file=sys.stderr)
        return 2
    except grpc.RpcError as e:
        print(f"grpc_client: {e.code().name}: {e.details()}", file=sys.stderr)
        return 1
    args.out.write_bytes(png)
    print(f"{args.out}: {len(png)} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
