"""Gaussians as SPZ, Niantic's compressed splat format (version 3, the gzip form every SPZ reader takes).

Written from the format's published description and checked against the reference implementation's behaviour
(github.com/nianticlabs/spz, ``load-spz.cc``; docs/DECISIONS.md, "Compact splat files"). A file is a gzip
stream of a 16-byte little-endian header

    magic u32 = 0x5053474e ("NGSP")  version u32 = 3  numPoints u32  shDegree u8  fractionalBits u8
    flags u8 (0x1: antialiased)  reserved u8 = 0

followed by the attributes, each one block for all points, in this order:

    positions  [N, 3] 24-bit signed fixed point, ``fractionalBits`` fractional bits (the reference writes 12)
    alphas     [N]    u8, round(sigmoid(opacity logit) * 255)
    colors     [N, 3] u8, round(sh0 * 0.15 * 255 + 127.5)   (SH DC, "wide" colour)
    scales     [N, 3] u8, round((log sigma + 10) * 16)
    rotations  [N, 4] u32: smallest three of the unit quaternion (xyzw, largest made positive), 1 sign bit and
                      9 magnitude bits each over [0, 1/sqrt 2], the largest's index in the top 2 bits
    sh         [N, K-1, 3] u8, round(c * 128) + 128 snapped to 2^(8-5) buckets for band 1 and 2^(8-4) above,
                      colour the inner axis (the same order as our ``shN``)

SPZ stores RUB axes (x right, y up, z back: OpenGL / three.js); a 3DGS PLY, like ours, is RDF (the COLMAP
camera convention). The change is a 180 degree turn about x: y and z of positions, the quaternion's y and z,
and the SH coefficients that are odd in y or z change sign (the reference's ``flipSh`` for RDF -> RUB).
``export_spz`` turns RDF into RUB and ``read_spz`` back, so a round trip returns our frame.

Worst-case error of a round trip (what tests/splat/test_spz.py asserts): position 2^-(fb+1) per axis (1.2e-4 at
fb = 12), log-scale 1/32 inside [-10, 5.94] (clamped outside), opacity 0.5/255, SH DC 0.5/38.25 = 0.0131
inside [-3.33, 3.33] (clamped outside: colour 0.5 +- 0.94), SH band 1 4.5/128, bands 2-3 8.5/128 inside
[-1, 1], rotation 4.8e-3 rad.
"""

from __future__ import annotations

import gzip
import logging
import math
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from pipeline.splat.gaussians import check_gaussians
from pipeline.splat.ply import write_atomic

log = logging.getLogger(__name__)

SPZ_MAGIC = 0x5053474E  # "NGSP" in file order
SPZ_VERSION = 3  # smallest-three quaternions, gzip; version 4 (zstd streams) is newer than most viewers
FRACTIONAL_BITS = 12  # the reference's choice: 1/4096 of a scene unit
COLOR_SCALE = 0.15  # SH DC -> u8 gain (reference ``colorScale``)
SH1_BITS, SH_REST_BITS = 5, 4  # the reference's default quantisation of SH band 1 and bands 2+
FLAG_ANTIALIASED = 0x1
_HEADER = struct.Struct("<IIIBBBB")  # 16 bytes
_FIXED_MAX = (1 << 23) - 1  # largest 24-bit signed value
_SQRT1_2 = math.sqrt(0.5)
_ROT_MASK = (1 << 9) - 1

# RDF <-> RUB sign of each higher SH coefficient (index k-1 of shN for basis k = 1..15; x kept, y and z negated).
_SH_SIGNS_RDF_RUB = np.array(
    [-1, -1, 1]  # band 1: y, z, x
    + [-1, 1, 1, -1, 1]  # band 2: xy, yz, 3z^2-1, xz, x^2-y^2
    + [-1, 1, -1, -1, 1, -1, 1],  # band 3
    dtype=np.float32,
)


def _rdf_rub_signs(n_rest: int) -> np.ndarray:
    """[K-1, 1] signs of the shN rows under the RDF <-> RUB turn (its own inverse)."""
    return _SH_SIGNS_RDF_RUB[:n_rest, None]


def _sh_degree(n_rest: int) -> int:
    degree = {0: 0, 3: 1, 8: 2, 15: 3}.get(n_rest)
    if degree is None:
        raise ValueError(f"shN with {n_rest} coefficients per channel is not SH degree 0..3")
    return degree


def _round(x: np.ndarray) -> np.ndarray:
    """Round half away from zero, as C's ``std::round`` in the reference (numpy's ``rint`` rounds half to even)."""
    return np.copysign(np.floor(np.abs(x) + 0.5), x)


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(_round(x), 0, 255).astype(np.uint8)


def _fractional_bits(means: np.ndarray) -> int:
    """12 unless the farthest coordinate would overflow 24 bits; then fewer (readers take it from the header)."""
    reach = float(np.abs(means).max(initial=0.0))
    fb = FRACTIONAL_BITS
    while fb > 0 and reach * (1 << fb) > _FIXED_MAX:
        fb -= 1
    if fb < FRACTIONAL_BITS:
        log.info("spz: coordinates reach %.4g, %d fractional bits instead of %d", reach, fb, FRACTIONAL_BITS)
    return fb


def _pack_positions(means: np.ndarray, fb: int) -> np.ndarray:
    """[N, 3] float -> [N, 9] u8 (24-bit little-endian two's complement per axis)."""
    fixed = _round(means.astype(np.float64) * (1 << fb))
    over = int((np.abs(fixed) > _FIXED_MAX).any(axis=1).sum())
    if over:
        log.warning("spz: %d Gaussians lie beyond +-%.4g and are clamped to it", over, _FIXED_MAX / (1 << fb))
    fixed = np.clip(fixed, -_FIXED_MAX, _FIXED_MAX).astype(np.int32)  # [N, 3]
    b = fixed.astype("<i4").view(np.uint8).reshape(-1, 3, 4)[:, :, :3]  # low three bytes
    return np.ascontiguousarray(b).reshape(-1, 9)


def _unpack_positions(raw: np.ndarray, fb: int) -> np.ndarray:
    """[N, 9] u8 -> [N, 3] float32."""
    b = raw.reshape(-1, 3, 3).astype(np.int32)
    fixed = b[:, :, 0] | (b[:, :, 1] << 8) | (b[:, :, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)  # sign extension
    return (fixed.astype(np.float64) / (1 << fb)).astype(np.float32)


def _pack_rotations(q_xyzw: np.ndarray) -> np.ndarray:
    """[N, 4] float32 unit quaternions (xyzw) -> [N, 4] u8: the reference's smallest-three code, little-endian."""
    n = len(q_xyzw)
    largest = np.abs(q_xyzw).argmax(axis=1)  # [N]
    flip = np.where(q_xyzw[np.arange(n), largest] < 0, np.float32(-1), np.float32(1))[:, None]  # -q: same rotation
    q = q_xyzw * flip
    comp = largest.astype(np.uint32)
    for i in range(4):  # ascending component order: the first one kept ends in the highest bits
        keep = largest != i
        neg = (q[:, i] < 0).astype(np.uint32)
        mag = (np.float32(_ROT_MASK) * (np.abs(q[:, i]) / np.float32(_SQRT1_2)) + np.float32(0.5)).astype(np.uint32)
        mag = np.minimum(mag, _ROT_MASK)  # |q_i| <= 1/sqrt 2 for a non-largest one, up to float error
        comp = np.where(keep, (comp << 10) | (neg << 9) | mag, comp)
    return comp.astype("<u4").view(np.uint8).reshape(n, 4)


def _unpack_rotations(raw: np.ndarray) -> np.ndarray:
    """[N, 4] u8 -> [N, 4] float32 unit quaternions (xyzw)."""
    comp = raw.reshape(-1, 4).copy().view("<u4").reshape(-1).astype(np.uint32)
    largest = comp >> 30
    q = np.zeros((len(comp), 4), dtype=np.float64)
    for i in range(3, -1, -1):
        keep = largest != i
        mag = (comp & _ROT_MASK).astype(np.float64) * (_SQRT1_2 / _ROT_MASK)
        sign = np.where((comp >> 9) & 1, -1.0, 1.0)
        q[:, i] = np.where(keep, sign * mag, 0.0)
        comp = np.where(keep, comp >> 10, comp)
    rest = 1.0 - (q * q).sum(axis=1)
    q[np.arange(len(q)), largest] = np.sqrt(np.clip(rest, 0.0, None))
    return q.astype(np.float32)


def _quantize_sh(x: np.ndarray, bits: int) -> np.ndarray:
    """The reference's ``quantizeSH``: 8-bit code round(x * 128) + 128 snapped to a multiple of 2^(8-bits)."""
    bucket = 1 << (8 - bits)
    q = _round(x * 128.0) + 128.0
    q = np.floor((q + bucket // 2) / bucket) * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


def _pack_rotations_v2(q_xyzw: np.ndarray) -> np.ndarray:
    """[N, 4] float32 unit quaternions (xyzw) -> [N, 3] u8: version 2's x, y, z with w made positive."""
    half = np.float32(127.5)
    sign = np.where(q_xyzw[:, 3:] < 0, -half, half)
    return _to_u8(q_xyzw[:, :3] * sign + half)


def export_spz(
    params: dict[str, Tensor],
    path: str | os.PathLike[str] | None = None,
    *,
    antialiased: bool = False,
    version: int = SPZ_VERSION,
) -> bytes:
    """Serialise Gaussian parameters (``pipeline.splat.gaussians`` layout, raw) to SPZ bytes.

    ``version`` 3 (the default) stores rotations as the smallest three components (10 bits each); 2 stores x, y,
    z in 8 bits each with w derived, far coarser where w is small, for readers that stop at version 2
    (GaussianSplats3D 0.4.7).

    Non-finite values cannot be stored: they are counted, logged and written as 0 (the PLY keeps them as they
    are). If ``path`` is given the bytes are also written there (atomically: temp file, then rename).
    """
    n = check_gaussians(params)
    if version not in (2, 3):
        raise ValueError(f"SPZ version {version} is not written here (2 and 3 are)")
    with torch.no_grad():
        a = {k: params[k].detach().to("cpu", torch.float32).numpy() for k in params}
    shn = a["shN"]  # [N, K-1, 3]
    degree = _sh_degree(shn.shape[1])
    table = np.concatenate(
        [a["means"], a["scales"], a["quats"], a["opacities"][:, None], a["sh0"].reshape(n, 3), shn.reshape(n, -1)],
        axis=1,
    )  # [N, F] for the non-finite count only
    bad = ~np.isfinite(table).all(axis=1)
    if bad.any():
        log.warning("export_spz: %d of %d Gaussians have non-finite values (written as 0)", int(bad.sum()), n)

    def finite(x: np.ndarray) -> np.ndarray:
        return np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)

    turn = np.array([1.0, -1.0, -1.0], dtype=np.float32)  # RDF -> RUB
    means = finite(a["means"]) * turn  # [N, 3]
    fb = _fractional_bits(means)

    # float32 and the reference's order of operations, so our codes equal the reference's bit for bit
    q = finite(a["quats"])[:, [1, 2, 3, 0]]  # [N, 4] xyzw
    x, y, z, w = q.T
    norm = np.sqrt(((x * x + y * y) + z * z) + w * w)[:, None]  # [N, 1]
    degenerate = norm[:, 0] == 0
    if degenerate.any():
        log.warning("export_spz: %d zero quaternions written as the identity", int(degenerate.sum()))
    identity = np.array([0.0, 0.0, 0.0, 1.0], dtype=np.float32)
    q = np.where(degenerate[:, None], identity, q / np.where(norm > 0, norm, np.float32(1.0)))
    q_xyzw = q * np.array([1.0, -1.0, -1.0, 1.0], dtype=np.float32)  # the turn about x keeps x and w

    logit = np.clip(finite(a["opacities"]).astype(np.float64), -100.0, 100.0)  # beyond: 0 or 1 in float64 anyway
    alpha = 1.0 / (1.0 + np.exp(-logit))  # [N]
    sh_rest = finite(shn) * _rdf_rub_signs(shn.shape[1])  # [N, K-1, 3]
    sh = np.empty(sh_rest.shape, dtype=np.uint8)
    sh[:, :3] = _quantize_sh(sh_rest[:, :3], SH1_BITS)
    sh[:, 3:] = _quantize_sh(sh_rest[:, 3:], SH_REST_BITS)

    header = _HEADER.pack(SPZ_MAGIC, version, n, degree, fb, FLAG_ANTIALIASED if antialiased else 0, 0)
    body = b"".join(
        [
            header,
            _pack_positions(means, fb).tobytes(),
            _to_u8(alpha * 255.0).tobytes(),
            _to_u8(finite(a["sh0"]).reshape(n, 3) * (COLOR_SCALE * 255.0) + 127.5).tobytes(),
            _to_u8((finite(a["scales"]) + 10.0) * 16.0).tobytes(),
            (_pack_rotations(q_xyzw) if version >= 3 else _pack_rotations_v2(q_xyzw)).tobytes(),
            sh.tobytes(),
        ]
    )
    data = gzip.compress(body, compresslevel=6, mtime=0)  # the reference's level; mtime 0: same Gaussians, same bytes
    if path is not None:
        write_atomic(path, data)
    return data


def spz_header(data: bytes) -> dict[str, int]:
    """The header fields of an SPZ version 1-3 file (gzip), decompressing only its first 16 bytes."""
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    head = d.decompress(data, _HEADER.size)
    if len(head) < _HEADER.size:
        raise ValueError("not an SPZ file: fewer than 16 bytes after gunzip")
    magic, version, n, degree, fb, flags, _ = _HEADER.unpack(head)
    if magic != SPZ_MAGIC:
        raise ValueError(f"not an SPZ file: magic {magic:#010x}, expected {SPZ_MAGIC:#010x}")
    return {"version": version, "num_points": n, "sh_degree": degree, "fractional_bits": fb, "flags": flags}


def read_spz(src: str | os.PathLike[str] | bytes | bytearray | memoryview) -> dict[str, Tensor]:
    """Read an SPZ file (versions 2 and 3, gzip) into the raw parameter layout of ``pipeline.splat.gaussians``,
    in our RDF frame. Returns float32 CPU tensors.

    Opacity codes 0 and 255 decode to the logit of 0.5/255 and 254.5/255 (the reference gives +-inf there);
    the stored alpha is kept within half a code either way.
    """
    buf = Path(src).read_bytes() if isinstance(src, (str, os.PathLike)) else bytes(src)
    if buf[:4] == b"NGSP":
        raise ValueError("SPZ version 4 (zstd streams) is not read here; versions 2 and 3 (gzip) are")
    if buf[:2] != b"\x1f\x8b":
        raise ValueError("not an SPZ file: no gzip magic")
    info = spz_header(buf)
    n, degree, fb, version = info["num_points"], info["sh_degree"], info["fractional_bits"], info["version"]
    if version not in (2, 3):
        raise ValueError(f"SPZ version {version} is not supported (2 and 3 are)")
    if degree > 3:
        raise ValueError(f"SH degree {degree} is not supported (0..3)")
    if fb > 23:
        raise ValueError(f"fractionalBits {fb} leaves no integer part in 24 bits")
    n_rest = (degree + 1) ** 2 - 1
    rot_bytes = 4 if version >= 3 else 3
    sizes = [9 * n, n, 3 * n, 3 * n, rot_bytes * n, 3 * n_rest * n]
    need = _HEADER.size + sum(sizes)
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    body = d.decompress(buf, need)  # bounded: a header that lies cannot make us inflate more than it claims
    if len(body) < need:
        raise ValueError(f"truncated SPZ: {n} points need {need} bytes after gunzip, got {len(body)}")
    blocks, at = [], _HEADER.size
    for size in sizes:
        blocks.append(np.frombuffer(body, dtype=np.uint8, count=size, offset=at))
        at += size
    pos, alpha, color, scale, rot, sh = blocks

    turn = np.array([1.0, -1.0, -1.0], dtype=np.float32)  # RUB -> RDF (the same turn)
    means = _unpack_positions(pos, fb) * turn
    if version >= 3:
        q_xyzw = _unpack_rotations(rot)
    else:  # version 2: x, y, z as round((q * 127.5) + 127.5) with w >= 0 derived
        xyz = rot.reshape(n, 3).astype(np.float32) * np.float32(1 / 127.5) - np.float32(1)  # float32 as the reference
        x, y, z = xyz.T
        w = np.sqrt(np.maximum(np.float32(1) - (x * x + y * y + z * z), np.float32(0)))
        q_xyzw = np.concatenate([xyz, w[:, None]], axis=1)
    q_xyzw = q_xyzw * np.array([1.0, -1.0, -1.0, 1.0], dtype=np.float32)
    a = np.clip(alpha.astype(np.float64) / 255.0, 0.5 / 255.0, 254.5 / 255.0)
    shn = (sh.reshape(n, n_rest, 3).astype(np.float32) - 128.0) / 128.0 * _rdf_rub_signs(n_rest)
    out = {
        "means": means,
        "scales": scale.reshape(n, 3).astype(np.float32) / 16.0 - 10.0,
        "quats": q_xyzw[:, [3, 0, 1, 2]],
        "opacities": np.log(a / (1.0 - a)).astype(np.float32),
        "sh0": ((color.reshape(n, 1, 3).astype(np.float32) / 255.0 - 0.5) / COLOR_SCALE),
        "shN": shn,
    }
    return {k: torch.from_numpy(np.ascontiguousarray(v, dtype=np.float32)) for k, v in out.items()}
