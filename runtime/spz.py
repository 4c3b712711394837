"""Niantic's SPZ (github.com/nianticlabs/spz), the compressed Gaussian-splat file, written as its version 3.

Version 3 is the gzip container: one gzip stream of a 16-byte header and the packed attributes. The reference
library (v4.x) still reads it, and writes a zstd container (version 4) by default; version 3 is what every SPZ
reader (three.js/Spark, the reference library old and new, gsply) opens, and it needs no zstd (the serving install
has none). The layout, all little endian (docs/conventions.md "Exchange formats"):

    header:    magic u32 0x5053474e ("NGSP") | version u32 = 3 | count u32 | SH degree u8 |
                    fractional bits u8 | flags u8 (0x1: trained antialiased; 0 here) | reserved u8 = 0
    then section after section, Gaussian after Gaussian:
      positions  3 x 24-bit signed fixed point: round(p * 2^fractional_bits)   (12 bits: 0.24 mm, +-2 km)
      alphas     u8 round(255 * sigmoid(opacity logit))
      colours    3 x u8 round(255 * (0.5 + 0.15 * dc))   (the SH DC coefficients, a little beyond [0, 1])
      scales     3 x u8 round(16 * (log scale + 10))       (e ^ (1/16) steps from e^-10 m)
      rotations  u32 "smallest three": the unit quaternion (xyzw) with its largest component made positive, that
                 component's index in bits 30-31, the other three in index order in bits 20-29, 10-19, 0-9, each
                 as sign bit << 9 | round(511 * |q_i| * sqrt 2)
      sh         the bands above DC: coefficient-major, channel inner, u8 round(128 * c) + 128, rounded to the
                 bucket of ``sh1_bits`` (degree 1) / ``sh_rest_bits`` (degrees 2-3) bits (as the reference: 5 / 4)

The coordinates are written as given: SPZ's frame is RUB (x right, y up, z back: OpenGL, three.js), which
runtime.exports converts the ego frame to (the one place that does). The quantisation steps, which bound what a
round trip loses (tests/runtime/test_exports.py), are in the constants below."""

from __future__ import annotations

import math
import struct

import numpy as np

from .errors import FieldError
from .render import Gaussians

MAGIC = 0x5053474E
VERSION = 3
COLOR_SCALE = 0.15                 # colour byte = 255 * (0.5 + COLOR_SCALE * dc)
SCALE_STEPS_PER_LOG = 16.0         # scale byte = 16 * (log scale + 10)
SCALE_LOG_MIN = -10.0
FRACTIONAL_BITS = 12               # positions: 2^-12 m = 0.24 mm steps, while every coordinate fits in 24 bits
SH1_BITS, SH_REST_BITS = 5, 4      # the reference library's defaults
_HEADER = struct.Struct("<IIIBBBB")


class SpzError(FieldError):
    """Gaussians SPZ cannot hold (``field`` the array or option at fault)."""


def _u8(x: np.ndarray) -> np.ndarray:
    """Round half up and clamp to a byte (C's round, as the reference: they differ only below 0, clamped to 0)."""
    return np.clip(np.floor(x + 0.5), 0, 255).astype(np.uint8)


def fractional_bits(means: np.ndarray) -> int:
    """The fixed point's fractional bits for positions ``means`` [N, 3] metres: FRACTIONAL_BITS unless a coordinate
    would overflow 24 bits, then fewer (each bit fewer doubles the step and the reach); SpzError when even 0 bits
    cannot hold them (farther than 8388 km)."""
    reach = float(np.abs(means).max()) if len(means) else 0.0
    bits = FRACTIONAL_BITS
    while bits >= 0 and reach * 2.0 ** bits >= 2 ** 23 - 1:
        bits -= 1
    if bits < 0:
        raise SpzError("means", f"a coordinate {reach:.0f} m from the origin is beyond SPZ's 24-bit reach")
    return bits


def pack_rotations(quats_wxyz: np.ndarray) -> np.ndarray:
    """[N] uint32 "smallest three" codes of quaternions [N, 4] wxyz (any non-zero norm; module docstring)."""
    q = np.asarray(quats_wxyz, np.float64)[:, [1, 2, 3, 0]]                 # SPZ's order: xyzw
    n = len(q)
    q /= np.sqrt(np.einsum("ij,ij->i", q, q))[:, None]
    big = np.argmax(np.abs(q), axis=1)
    rows = np.arange(n)
    q *= np.where(q[rows, big] < 0, -1.0, 1.0)[:, None]
    keep = np.ones((n, 4), bool)
    keep[rows, big] = False
    rest = q[keep].reshape(n, 3)                                             # the other three, in index order
    mag = np.minimum(np.floor(np.abs(rest) * (511.0 * math.sqrt(2.0)) + 0.5), 511).astype(np.uint32)
    c = ((rest < 0).astype(np.uint32) << np.uint32(9)) | mag
    return ((big.astype(np.uint32) << np.uint32(30)) | (c[:, 0] << np.uint32(20)) | (c[:, 1] << np.uint32(10))
            | c[:, 2])


def _sh_bytes(rest: np.ndarray, sh1_bits: int, sh_rest_bits: int) -> np.ndarray:
    """[N, K - 1, 3] SH bands above DC -> uint8 codes, each rounded to its degree's bucket."""
    q = np.floor(rest.astype(np.float64) * 128.0 + 0.5) + 128.0
    bucket = np.full(rest.shape[1], 1 << (8 - sh_rest_bits), np.float64)
    bucket[:3] = 1 << (8 - sh1_bits)
    b = bucket[None, :, None]
    return np.clip(np.floor((q + b // 2) / b) * b, 0, 255).astype(np.uint8)


def spz_payload(g: Gaussians, sh1_bits: int = SH1_BITS, sh_rest_bits: int = SH_REST_BITS) -> tuple[bytes, bytes]:
    """(the 16-byte header, the uncompressed payload) of Gaussians ``g`` (its frame is the file's: RUB for
    readers that take SPZ as the reference does; runtime.exports converts)."""
    for name, bits in (("sh1_bits", sh1_bits), ("sh_rest_bits", sh_rest_bits)):
        if not 1 <= bits <= 8:
            raise SpzError(name, f"must be 1..8 bits (got {bits})")
    if len(g) >= 2 ** 32:
        raise SpzError("means", f"{len(g)} Gaussians: SPZ counts them in 32 bits")
    n, bits = len(g), fractional_bits(g.means)
    # exact in float32 too: scaling by 2^bits is exact and |value| < 2^23 keeps + 0.5 exact
    fixed = np.floor(g.means * g.means.dtype.type(2.0 ** bits) + g.means.dtype.type(0.5)).astype("<i4")
    positions = fixed.reshape(n, 3, 1).view(np.uint8).reshape(n, 3, 4)[:, :, :3]     # the low 3 bytes (LE)
    alphas = _u8(255.0 / (1.0 + np.exp(-np.asarray(g.opacity_logits, np.float32))))    # float32: < 1e-4 of a step
    colours = _u8(np.float32(255.0 * COLOR_SCALE) * g.sh[:, 0, :] + np.float32(127.5))
    scales = _u8(np.float32(SCALE_STEPS_PER_LOG) * (g.log_scales - np.float32(SCALE_LOG_MIN)))
    rotations = pack_rotations(g.quats).astype("<u4").view(np.uint8)
    sh = _sh_bytes(g.sh[:, 1:, :], sh1_bits, sh_rest_bits)
    header = _HEADER.pack(MAGIC, VERSION, n, g.sh_degree, bits, 0, 0)
    body = b"".join(np.ascontiguousarray(a).tobytes() for a in (positions, alphas, colours, scales, rotations, sh))
    return header, body


def spz_bytes(g: Gaussians, sh1_bits: int = SH1_BITS, sh_rest_bits: int = SH_REST_BITS) -> bytes:
    """An SPZ version 3 file of Gaussians ``g`` (module docstring): the header and payload, gzip-compressed as one
    stream (ISA-L's deflate, a base dependency: several times zlib's speed for a few per cent in size)."""
    from isal import igzip

    header, body = spz_payload(g, sh1_bits, sh_rest_bits)
    return igzip.compress(header + body, compresslevel=2, mtime=0)


__all__ = ["SpzError", "fractional_bits", "pack_rotations", "spz_bytes", "spz_payload"]
