"""Image files the runtime reads and writes: EXR read back (runtime.rig.read_image) and 8-bit PNG
(runtime.png.encode_png, the service's encoder). The EXR writer is xyzcyl.common.media.write_exr (one for the
runtime, the server and the client)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

LUMA_BT601 = np.array([0.299, 0.587, 0.114], np.float32)   # ITU-R BT.601 luma weights (JPEG's Y of sRGB values)


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """[H, W, C] float32 of an EXR (or any float image OpenImageIO reads); OSError naming the file."""
    from .rig import RigError, read_image

    try:
        return read_image(Path(path), f"file {str(path)!r}", channels=3, scale=False)
    except RigError as e:
        raise OSError(str(e)) from None


def write_png(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """[H, W, 3] float RGB in 0..1 -> 8-bit RGB PNG: round(255 x) clipped, NaN 0 (exact, float64), encoded by
    runtime.png.encode_png as the service encodes an rgb view (PNG_FILTERS["rgb"], ISA-L deflate). OSError
    when the file cannot be written."""
    from .png import PNG_FILTERS, encode_png, to_u8

    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"write_png: expected [H, W, 3] RGB, got {list(a.shape)}")
    data = encode_png(to_u8(a), PNG_FILTERS["rgb"])
    try:
        Path(path).write_bytes(data)
    except OSError as e:
        raise OSError(f"cannot write {path}: {e.strerror or e}") from None
