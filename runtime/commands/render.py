"""`xyzcyl render PLY ...`: render a 3DGS PLY (INRIA layout) from one camera pose to PNG (RGB) or EXR
(float32 channels R G B A Z; Z = expected depth in metres, 0 where A == 0). See docs/renderer.md."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("ply", metavar="PLY", help="Gaussians in the 3DGS PLY layout (world = ego frame)")
    parser.add_argument("--width", type=int, required=True, help="image width, pixels")
    parser.add_argument("--height", type=int, required=True, help="image height, pixels")
    parser.add_argument("--K", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                        help="pinhole intrinsics in pixels, OpenCV (pixel u is centred at x = u); required "
                             "unless --equirect")
    parser.add_argument("--cam-to-world", type=float, nargs=16, required=True, metavar="M",
                        help="4x4 camera-to-world matrix, row-major (OpenCV camera: x right, y down, z forward)")
    parser.add_argument("--out", required=True, metavar="PATH", help="output .png (RGB, 8 bit) or .exr "
                        "(float32 R G B A Z)")
    parser.add_argument("--background", type=float, nargs=3, default=None, metavar=("R", "G", "B"),
                        help="background colour in 0..1 (default black)")
    parser.add_argument("--equirect", action="store_true",
                        help="render a full 360x180 equirectangular panorama instead (K not used)")
    parser.add_argument("--antialiased", action="store_true", help="gsplat's antialiased opacity compensation")
    parser.add_argument("--max-points", type=int, default=None, help="refuse PLYs with more Gaussians")


def _fail(msg: str) -> int:
    print(f"xyzcyl render: {msg}", file=sys.stderr)
    return 2


def write_exr(path: str, channels: np.ndarray, names: tuple[str, ...]) -> None:
    """channels [H, W, C] float32 -> EXR. OpenImageIO needs a C-contiguous array (it returns False and writes
    a broken file otherwise), so the array is made contiguous and every return value is checked."""
    import OpenImageIO as oiio

    data = np.ascontiguousarray(channels, dtype=np.float32)
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, oiio.FLOAT)
    spec.channelnames = names
    out = oiio.ImageOutput.create(path)
    if out is None:
        raise OSError(f"cannot create an EXR writer for {path}: {oiio.geterror()}")
    ok = out.open(path, spec) and out.write_image(data)
    err = out.geterror() if not ok else ""
    closed = out.close()
    if not ok or not closed:
        raise OSError(f"writing {path} failed: {err or oiio.geterror()}")


def run(args: argparse.Namespace) -> int:
    from ..render import CameraError, EquirectCamera, GaussianError, Gaussians, PinholeCamera, render
    from ..render.gaussians import DEFAULT_MAX_POINTS

    out = Path(args.out)
    suffix = out.suffix.lower()
    if suffix not in (".png", ".exr"):
        return _fail(f"--out: extension must be .png or .exr, got {out.suffix or 'none'!r}")
    if not out.parent.is_dir():
        return _fail(f"--out: folder {str(out.parent)!r} does not exist")
    if args.background is not None and not all(np.isfinite(args.background)):
        return _fail("--background: values must be finite")
    if not args.equirect and args.K is None:
        return _fail("--K: required for a pinhole camera (or pass --equirect)")
    if not Path(args.ply).is_file():
        return _fail(f"PLY: no such file {args.ply!r}")
    max_points = DEFAULT_MAX_POINTS if args.max_points is None else args.max_points
    try:
        c2w = np.array(args.cam_to_world, dtype=np.float64).reshape(4, 4)
        if args.equirect:
            cam = EquirectCamera(c2w, args.width, args.height)
        else:
            fx, fy, cx, cy = args.K
            cam = PinholeCamera(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), c2w, args.width, args.height)
    except CameraError as exc:
        field = str(exc).split(":")[0]
        flag = {"cam_to_world": "--cam-to-world", "K": "--K"}.get(field, f"--{field}")
        return _fail(f"{flag}: {str(exc).split(': ', 1)[-1]}")
    try:
        g = Gaussians.load_ply(args.ply, max_points=max_points)
    except GaussianError as exc:
        return _fail(f"PLY: {exc}")
    res = render(g, cam, background=args.background, antialiased=args.antialiased)
    try:
        if suffix == ".png":
            import cv2

            rgb8 = np.clip(np.rint(res.rgb * 255.0), 0, 255).astype(np.uint8)
            if not cv2.imwrite(str(out), np.ascontiguousarray(rgb8[..., ::-1])):
                raise OSError(f"cv2 could not write {out}")
        else:
            write_exr(str(out), np.dstack([res.rgb, res.alpha, res.depth]), ("R", "G", "B", "A", "Z"))
    except OSError as exc:
        return _fail(f"--out: {exc}")
    print(f"rendered {len(g)} Gaussians -> {out} ({args.width}x{args.height}, "
          f"coverage {float((res.alpha > 0).mean()):.3f})")
    return 0
