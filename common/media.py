"""Image files by their content: the one content sniffer (PNG, JPEG, EXR and TIFF by their magic bytes), the media
types by file suffix, and the one EXR writer (float32 channels through OpenImageIO, to a file or to bytes).

Used by the server (the type of an uploaded part), the HTTP client (the type of a part it sends, an EXR answer)
and the runtime (scene backgrounds, EXR views and renders)."""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Media:
    """An image file type: its media type, the suffix the project writes it with, and its name for messages."""

    type: str
    suffix: str
    name: str


PNG = Media("image/png", ".png", "PNG")
JPEG = Media("image/jpeg", ".jpg", "JPEG")
EXR = Media("image/x-exr", ".exr", "EXR")
TIFF = Media("image/tiff", ".tif", "TIFF")

SNIFF_BYTES = 16          # enough of a file's start for sniff()
_MAGIC = ((b"\x89PNG\r\n\x1a\n", PNG), (b"\xff\xd8\xff", JPEG), (b"\x76\x2f\x31\x01", EXR), (b"II*\x00", TIFF),
          (b"MM\x00*", TIFF))
_BY_SUFFIX = {".png": PNG, ".jpg": JPEG, ".jpeg": JPEG, ".exr": EXR, ".tif": TIFF, ".tiff": TIFF}


def sniff(head: bytes) -> Media | None:
    """The image type that a file's first bytes (SNIFF_BYTES suffice) show, or None for anything else."""
    for magic, media in _MAGIC:
        if head.startswith(magic):
            return media
    return None


def media_of_suffix(suffix: str) -> Media | None:
    """The image type of a file suffix (".png", ".JPG", ...; any case), or None."""
    return _BY_SUFFIX.get(suffix.lower())


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


def exr_bytes(channels: np.ndarray, names: tuple[str, ...], compression: str | None = None) -> bytes:
    """The bytes of the EXR that write_exr writes. OpenImageIO writes EXR to files only (its Python binding has no
    in-memory writer we rely on): a temporary folder, removed afterwards, also on errors."""
    with tempfile.TemporaryDirectory(prefix="xyzcyl-exr-") as tmp:
        path = Path(tmp) / "image.exr"
        write_exr(path, channels, names, compression=compression)
        return path.read_bytes()


__all__ = ["EXR", "JPEG", "PNG", "SNIFF_BYTES", "TIFF", "Media", "exr_bytes", "media_of_suffix", "sniff",
           "write_exr"]
