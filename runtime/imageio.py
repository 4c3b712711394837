"""Image files the runtime writes: EXR (float32 channels, OpenImageIO) and 8-bit PNG (OpenCV)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def write_exr(path: str | os.PathLike, channels: np.ndarray, names: tuple[str, ...],
              compression: str | None = None) -> None:
    """channels [H, W, C] float32 -> EXR. OpenImageIO needs a C-contiguous array (it returns False and writes
    a broken file otherwise), so the array is made contiguous and every return value is checked.
    ``compression``: an OpenEXR compression name ("none", "zip", "piz", ...); None = OpenImageIO's default (zip).
    Measured on this machine for a 1600x900 RGB render: zip 0.36 s for 5 % fewer bytes than none at 0.04 s."""
    import OpenImageIO as oiio

    path = str(path)
    data = np.ascontiguousarray(channels, dtype=np.float32)
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, oiio.FLOAT)
    spec.channelnames = names
    if compression is not None:
        spec.attribute("compression", compression)
    out = oiio.ImageOutput.create(path)
    if out is None:
        raise OSError(f"cannot create an EXR writer for {path}: {oiio.geterror()}")
    ok = out.open(path, spec) and out.write_image(data)
    err = out.geterror() if not ok else ""
    closed = out.close()
    if not ok or not closed:
        raise OSError(f"writing {path} failed: {err or oiio.geterror()}")


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """[H, W, C] float32 of an EXR (or any float image OpenImageIO reads); OSError naming the file."""
    from .rig import RigError, read_image

    try:
        return read_image(Path(path), f"file {str(path)!r}", channels=3, scale=False)
    except RigError as e:
        raise OSError(str(e)) from None


def write_png(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """[H, W, 3] float RGB in 0..1 -> 8-bit PNG (clipped, rounded); OSError when OpenCV cannot write it."""
    import cv2

    rgb8 = np.clip(np.rint(np.asarray(rgb, np.float32) * 255.0), 0, 255).astype(np.uint8)
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb8[..., ::-1])):
        raise OSError(f"cv2 could not write {path}")
