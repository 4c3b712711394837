"""Rigs for tests and benchmarks, and the multipart body of POST /v1/scenes (docs/api.md): a ``rig`` part (the rig
JSON) and one image part per camera, named by the camera, plus whatever extra parts (``depth:<camera>``,
``ego_mask:<camera>``, ``lidar``) a caller adds; or a recorded drive's (``drive_files``)."""

from __future__ import annotations

import functools
import json
import struct
import zlib
from pathlib import Path
from typing import Any

import xyzcyl.testing as _testing  # its EXAMPLE_RIG is found on first use (the source checkout's)

MEDIA_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}


@functools.cache
def read_rig(rig_json: Path | None = None) -> dict:
    """The rig JSON (None: the example rig) as a dict (cached: copy it before changing it)."""
    return json.loads(Path(rig_json or _testing.EXAMPLE_RIG).read_text())


@functools.cache
def rig_images(rig_json: Path | None = None) -> dict[str, bytes]:
    """{camera name: the bytes of its image file} of a rig (None: the example rig) (cached)."""
    rig_json = Path(rig_json or _testing.EXAMPLE_RIG)
    return {c["name"]: (rig_json.parent / c["image"]).read_bytes() for c in read_rig(rig_json)["cameras"]}


def example_rig() -> dict:
    """examples/synth_nuscenes/rig.json (6 cameras, 800x450 PNGs) as a dict (cached: copy it before changing it)."""
    return read_rig(_testing.EXAMPLE_RIG)


def example_images() -> dict[str, bytes]:
    """{camera name: PNG bytes} of the example rig (cached)."""
    return rig_images(_testing.EXAMPLE_RIG)


def rig_files(rig: dict | None = None, images: dict[str, Any] | None = None, rig_bytes: bytes | None = None,
              drop: tuple[str, ...] = (), extra: list | None = None, *, rig_json: Path | None = None) -> list:
    """The multipart parts of POST /v1/scenes (``files=`` of httpx or a TestClient): ("rig", rig.json) + one image
    part per camera of ``rig``, then ``extra``.

    ``rig_json`` is where the rig and its images come from (None: the example rig); ``rig`` replaces its
    JSON (``rig_bytes`` replaces the part's bytes as they are). A camera's part is its image file (named by the
    file, typed by its suffix) unless ``images`` gives its bytes (sent as ``<camera>.png``, image/png) or a whole
    (filename, bytes, media type) tuple; a camera the source rig does not have gets its first camera's image.
    ``drop`` leaves out parts by name ("rig" or a camera)."""
    rig_json = Path(rig_json or _testing.EXAMPLE_RIG)
    source = read_rig(rig_json)
    if rig_bytes is None:
        rig_bytes = rig_json.read_bytes() if rig is None else json.dumps(rig).encode()
    rig = source if rig is None else rig
    data = rig_images(rig_json)
    imgs = {c["name"]: (Path(c["image"]).name, data[c["name"]],
                        MEDIA_TYPES.get(Path(c["image"]).suffix.lower(), "application/octet-stream"))
            for c in source["cameras"]}
    imgs.update(images or {})
    first = imgs[source["cameras"][0]["name"]]
    parts = []
    if "rig" not in drop:
        parts.append(("rig", ("rig.json", rig_bytes, "application/json")))
    for c in rig["cameras"]:
        if c["name"] in drop:
            continue
        img = imgs.get(c["name"], first)
        parts.append((c["name"], img if isinstance(img, tuple) else (f"{c['name']}.png", img, "image/png")))
    return parts + list(extra or [])


def drive_files(drive_json: Path, edit=None, drop: tuple[str, ...] = (), extra: list | None = None) -> list:
    """The multipart parts of POST /v1/scenes for a drive file (docs/api.md "Drives"; ``files=`` of httpx or a
    TestClient): the 'drive' part (each frame's rig and the tracks read and put inline; ``edit(doc)`` may change
    it), then each frame's image, depth and ego mask files and LiDAR sweep, as the frame's rig names them, in parts
    named ``frames/<frame>/<camera>``, ``.../depth:<camera>``, ``.../ego_mask:<camera>``, ``.../lidar``; then
    ``extra``. ``drop`` leaves out parts by name."""
    drive_json = Path(drive_json)
    doc = json.loads(drive_json.read_text())
    parts = []
    for i, entry in enumerate(doc["frames"]):
        rig_path = drive_json.parent / entry["rig"]
        rig = entry["rig"] = json.loads(rig_path.read_text())
        files = [(f"{prefix}{c['name']}", c.get(key)) for c in rig["cameras"]
                 for key, prefix in (("image", ""), ("depth", "depth:"), ("ego_mask", "ego_mask:"))]
        lidar = rig.get("lidar")
        files.append(("lidar", lidar.get("file") if isinstance(lidar, dict) else None))
        for name, file in files:
            if file:
                f = rig_path.parent / file
                media = "application/octet-stream" if name == "lidar" else MEDIA_TYPES.get(f.suffix.lower(),
                                                                                           "image/png")
                parts.append((f"frames/{i}/{name}", (f.name, f.read_bytes(), media)))
    if isinstance(doc.get("tracks"), str):
        doc["tracks"] = json.loads((drive_json.parent / doc["tracks"]).read_text())
    if edit is not None:
        edit(doc)
    parts.insert(0, ("drive", ("drive.json", json.dumps(doc).encode(), "application/json")))
    return [p for p in parts if p[0] not in drop] + list(extra or [])


def multipart_body(files: list) -> tuple[bytes, str]:
    """The encoded multipart/form-data body of ``files`` and its Content-Type (with the boundary)."""
    import httpx

    req = httpx.Request("POST", "http://x/v1/scenes", files=files)
    return req.read(), req.headers["content-type"]


def png_header_only(w: int, h: int) -> bytes:
    """A tiny PNG whose header claims w x h (a decompression bomb's shape: the server must refuse it from the
    header, before decoding)."""
    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b""))


def make_rig(work: Path, width: int = 1600, height: int = 900) -> Path:
    """The example rig at width x height, JPEG quality 90 (the issue's 6 x 1600x900 JPEG input), written once
    into ``work``/rig<width>/; its rig.json."""
    import cv2
    from xyzcyl.runtime.rig import Rig, load_rig, save_rig

    out = work / f"rig{width}"
    if (out / "rig.json").is_file():
        return out / "rig.json"
    out.mkdir(parents=True, exist_ok=True)
    rig = load_rig(_testing.EXAMPLE_RIG)
    cams = []
    for c in rig.cameras:
        img = cv2.imread(str(rig.path(c.image)), cv2.IMREAD_COLOR)
        big = cv2.resize(img, (width, height), interpolation=cv2.INTER_LINEAR)
        name = f"{c.name}.jpg"
        cv2.imwrite(str(out / name), big, [cv2.IMWRITE_JPEG_QUALITY, 90])
        cams.append(c.resized(width, height).replace(image=name))
    save_rig(Rig(cameras=tuple(cams), extra=rig.extra), out / "rig.json")
    return out / "rig.json"
