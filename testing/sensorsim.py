"""What the gRPC SensorsimService's tests and benchmark share (tests/server/test_grpc.py, benchmarks/grpc_bench.py):
the example scene's ego pose in a simulator's local frame, AlpaSim's render request for one camera, the HTTP query
of the same view, and the gRPC port a server logged. grpc and protobuf (the ``server`` extra) are needed."""

from __future__ import annotations

import json
import math
import re

import numpy as np
from xyzcyl.server.sensorsim import frames
from xyzcyl.server.sensorsim import sensorsim_pb2 as pb


def ego_pose() -> np.ndarray:
    """[4, 4] ego_to_world for the example scene: 30 degrees of yaw, 100 m out in the simulator's local frame."""
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    E = np.eye(4)
    E[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    E[:3, 3] = [100.0, -40.0, 0.3]
    return E


def rig_with_pose(rig: dict, ego_to_world: np.ndarray) -> dict:
    """A copy of the rig JSON ``rig`` with its top-level ``ego_to_world``."""
    out = json.loads(json.dumps(rig))
    out["ego_to_world"] = np.asarray(ego_to_world).tolist()
    return out


def grpc_port(log_text: str) -> int:
    """The port `xyzcyl serve --grpc-port 0` logged ("SensorsimService (gRPC) listening on HOST:PORT")."""
    m = re.search(r"SensorsimService \(gRPC\) listening on \S+:(\d+)", log_text)
    if m is None:
        raise ValueError("the server logged no SensorsimService port")
    return int(m.group(1))


def rgb_request(cam, start: np.ndarray, end: np.ndarray | None = None, scene: str = "", width: int = 512,
                height: int = 320, image_format: int = pb.PNG, time_us: int = 1_000_000,
                exposure_us: int = 30_000) -> pb.RGBRenderRequest:
    """AlpaSim's RGBRenderRequest for ``cam`` (an AvailableCamera of get_available_cameras) with the ego at
    ``start`` when the exposure starts and ``end`` when it ends (ego -> local frame; default: still): the sensor
    pose is the ego pose composed with the camera -> rig pose, as AlpaSim composes it. The exposure starts at
    ``time_us`` (microseconds on the rigs' clock) and lasts ``exposure_us``."""
    rig_cam = frames.pose_matrix(cam.rig_to_camera, "rig_to_camera")
    end = start if end is None else end
    pair = pb.PosePair(start_pose=frames.pose_message(start @ rig_cam), end_pose=frames.pose_message(end @ rig_cam))
    return pb.RGBRenderRequest(scene_id=scene, resolution_w=width, resolution_h=height,
                               camera_intrinsics=cam.intrinsics, frame_start_us=time_us,
                               frame_end_us=time_us + exposure_us,
                               sensor_pose=pair, image_format=image_format, image_quality=95)


def view_query(req: pb.RGBRenderRequest, ego_to_world: np.ndarray) -> dict:
    """The GET /v1/scenes/{id}/render query of the view the server makes of ``req`` for a scene at
    ``ego_to_world`` (frames.view_request, the server's one conversion; numbers written exactly)."""
    view = frames.view_request(req, ego_to_world)
    cam = view.camera
    K = cam.K
    out = {"cam_to_ego": ",".join(repr(float(v)) for v in cam.cam_to_ego.ravel()), "fx": repr(float(K[0, 0])),
           "fy": repr(float(K[1, 1])), "cx": repr(float(K[0, 2])), "cy": repr(float(K[1, 2])),
           "width": cam.width, "height": cam.height}
    if view.time_s is not None:         # the middle of the exposure (frames.exposure_time)
        out["time"] = repr(float(view.time_s))
    return out


__all__ = ["ego_pose", "grpc_port", "rgb_request", "rig_with_pose", "view_query"]
