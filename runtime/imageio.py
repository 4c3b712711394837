"""Image files the runtime writes: EXR (float32 channels, OpenImageIO) and 8-bit PNG (runtime.views.encode_png,
the service's encoder)."""

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
    spec.attribute("DateTime", "")   # no capture-date header (OpenImageIO stamps the wall clock): the bytes depend on
    #                                  the data only (the synthetic dataset's files are compared across runs)
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
    """[H, W, 3] float RGB in 0..1 -> 8-bit RGB PNG: round(255 x) clipped, NaN 0 (exact, float64), encoded by
    runtime.views.encode_png as the service encodes an rgb view (PNG_FILTERS["rgb"], ISA-L deflate). OSError
    when the file cannot be written."""
    from .views import PNG_FILTERS, _u8, encode_png

    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"write_png: expected [H, W, 3] RGB, got {list(a.shape)}")
    data = encode_png(_u8(a), PNG_FILTERS["rgb"])
    try:
        Path(path).write_bytes(data)
    except OSError as e:
        raise OSError(f"cannot write {path}: {e.strerror or e}") from None
