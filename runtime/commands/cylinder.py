"""`xyzcyl cylinder RIG_JSON --out PNG`: project a rig's images onto the UCCM cylinder (paper Sec. 3.1).

Prints the covered fraction (cylinder pixels valid in at least one camera) and each camera's coverage.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..cylinder import (
    DEFAULT_Z_RANGE,
    MODULES,
    PRESETS,
    CylinderError,
    CylinderSpec,
    coverage,
    overlay,
    project_rig,
)
from ..rig import RigError, load_rig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("rig", metavar="RIG_JSON", help="rig.json (docs/conventions.md); images relative to it")
    parser.add_argument("--out", required=True, metavar="PNG", help="output panorama (8-bit PNG, RGB)")
    parser.add_argument("--order", choices=("cw", "ccw"), default="cw",
                        help="overlay order: cw = F+ (later cameras overwrite), ccw = F- (default cw)")
    parser.add_argument("--height", type=int, default=224, help="H_u, cylinder rows (default 224)")
    parser.add_argument("--width", type=int, default=1024, help="W_u, cylinder columns (default 1024)")
    parser.add_argument("--z-range", type=float, nargs=2, default=list(DEFAULT_Z_RANGE), metavar=("ZMIN", "ZMAX"),
                        help="occupancy grid vertical range in ego metres; Z_u = ZMAX - ZMIN (default -3 13)")
    parser.add_argument("--rho", type=float, default=None,
                        help="FoV factor rho (default 0.9, or the preset's)")
    parser.add_argument("--dh", type=float, default=None, help="centre height offset, metres (default 0, or the "
                        "preset's)")
    parser.add_argument("--preset", choices=sorted(PRESETS), default=None,
                        help="take rho and dh from the paper's table for this dataset (unless --rho/--dh given)")
    parser.add_argument("--sort-clockwise", action="store_true",
                        help="reorder the cameras clockwise from the front before overlaying (default: rig order)")
    parser.add_argument("--module", choices=MODULES, default="occupancy",
                        help="which module's preset (rho, dh) to use with --preset (default occupancy)")


def _fail(msg: str) -> int:
    print(f"xyzcyl cylinder: {msg}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    rho, dh = 0.9, 0.0
    if args.preset is not None:
        rho, dh = PRESETS[args.preset][args.module]
    rho = rho if args.rho is None else args.rho
    dh = dh if args.dh is None else args.dh
    if not 0 < args.height <= 65536:
        return _fail(f"--height must be in 1..65536 (got {args.height})")
    if not 0 < args.width <= 65536:
        return _fail(f"--width must be in 1..65536 (got {args.width})")
    out = Path(args.out)
    if out.suffix.lower() != ".png":
        return _fail(f"--out must name a .png file (got {args.out!r})")
    try:
        rig = load_rig(args.rig, check_images=True)
        spec = CylinderSpec.from_rig(rig, z_range=tuple(args.z_range), rho=rho, dh=dh, height=args.height,
                                     width=args.width)
        if args.sort_clockwise:
            rig = rig.reordered(rig.clockwise_order())
        images = rig.load_images()
    except (RigError, CylinderError) as exc:
        return _fail(str(exc))
    maps, valid = project_rig(spec, rig, images)
    pano = overlay(maps, order=args.order, valid=valid)
    import cv2

    u8 = (np.clip(pano, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if not out.parent.is_dir():
        return _fail(f"--out: folder {str(out.parent)!r} does not exist")
    if not cv2.imwrite(str(out), np.ascontiguousarray(u8[..., ::-1])):
        return _fail(f"--out: cannot write {str(out)!r}")
    total, per = coverage(valid)
    print(f"cylinder: centre {np.round(spec.centre, 3).tolist()} m, R_u {spec.radius:.3f} m, Z_u {spec.Z_u:g} m, "
          f"rho {rho:g}, dh {dh:g}, {spec.height}x{spec.width}, order {args.order}")
    for cam, frac in zip(rig.cameras, per):
        print(f"  {cam.name}: {100 * frac:.2f}% of the cylinder")
    print(f"covered: {100 * total:.2f}% of cylinder pixels by >= 1 camera")
    print(f"wrote {out}")
    return 0
