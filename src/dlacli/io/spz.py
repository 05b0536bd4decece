"""Niantic's `.spz` (formats/spz.md): gzip of a 16-byte header and attribute blocks.

dla writes version 3 (gzip; rotations as "smallest three" in 4 bytes) and reads versions 2 and 3.
Version 4 (zstd streams) is not written: it needs a zstd codec, and the readers in the field read 3.

SPZ stores its data in RUB axes (x right, y up, z back; Niantic's spec), while 3DGS .ply data
is RDF (x right, y down, z forward). The writer and reader take and give Gaussians in the
PLY's frame, and flip y and z on the way (positions, quaternions, SH), as Niantic's own library
and PlayCanvas splat-transform do, so that an .spz and a .ply written from the same Gaussians
open the same way in a viewer.
"""

from __future__ import annotations

import gzip
import os
import struct
import zlib
from pathlib import Path

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.io.atomic import atomic_path
from dlacli.io.splat import checked_arrays, to_u8
from dlacli.types import Gaussians, sh_coeffs_for_degree

MAGIC = 0x5053474E  # "NGSP" little-endian
VERSION = 3
HEADER = struct.Struct("<IIIBBBB")  # magic, version, count, sh degree, fractional bits, flags, reserved
FRACTIONAL_BITS = 12  # positions in steps of 2^-12 m = 0.244 mm
COLOR_SCALE = 0.15  # colour byte = f_dc * 0.15 * 255 + 127.5
SQRT1_2 = 0.7071067811865476
MAX_POINTS = 1 << 25  # 33.5 M Gaussians (dla exports at most 4.2 M); bounds what a header can make the reader unpack

# RDF -> RUB is the 180-degree rotation about x: (x, y, z) -> (x, -y, -z). A real SH basis
# function of the 3DGS order (degree l, m = -l..l) is a polynomial in x, y, z of one parity in
# (y, z), so the rotation multiplies its coefficient by +-1 (checked in tests against the
# splatter's `sh_basis`). Index k - 1 for k = 1..15.
_SH_FLIP = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], dtype=np.float64)


def _flip_frame(means, quats, sh):
    """RDF <-> RUB (its own inverse): means [N, 3], quats [N, 4] (w, x, y, z), sh [N, K, 3]."""
    means = means * np.array([1.0, -1.0, -1.0])
    quats = quats * np.array([1.0, 1.0, -1.0, -1.0])
    k = sh.shape[1]
    sh = sh * np.concatenate([[1.0], _SH_FLIP[: k - 1]])[None, :, None]
    return means, quats, sh


def _pack_rotations(quats: np.ndarray) -> np.ndarray:
    """Unit quaternions [N, 4] (x, y, z, w order) -> [N, 4] uint8, "smallest three": the index of the
    largest |component| in the top 2 bits of a little-endian uint32, then, for the other three in
    order, a sign bit and a 9-bit magnitude |q_i| / sqrt(1/2) * 511 (the largest made positive)."""
    largest = np.argmax(np.abs(quats), axis=1)  # [N]
    sign = np.where(np.take_along_axis(quats, largest[:, None], 1) < 0, -1.0, 1.0)  # [N, 1]
    q = quats * sign
    comp = largest.astype(np.uint32)
    for i in range(4):
        keep = largest != i
        neg = (q[:, i] < 0).astype(np.uint32)
        mag = np.floor(511.0 * np.abs(q[:, i]) / SQRT1_2 + 0.5).astype(np.uint32)
        mag = np.minimum(mag, 511)  # |q_i| <= sqrt(1/2) for a non-largest component of a unit quaternion
        comp = np.where(keep, (comp << np.uint32(10)) | (neg << np.uint32(9)) | mag, comp)
    return comp.astype("<u4").view(np.uint8).reshape(-1, 4)


def _unpack_rotations(raw: np.ndarray) -> np.ndarray:
    """[N, 4] uint8 smallest-three -> unit quaternions [N, 4] (x, y, z, w order)."""
    comp = raw.copy().view("<u4")[:, 0].astype(np.uint64)  # [N]
    largest = (comp >> np.uint64(30)).astype(np.int64)
    q = np.zeros((raw.shape[0], 4))
    for i in range(3, -1, -1):
        keep = largest != i
        mag = (comp & np.uint64(511)).astype(np.float64) / 511.0 * SQRT1_2
        neg = ((comp >> np.uint64(9)) & np.uint64(1)).astype(bool)
        q[:, i] = np.where(keep, np.where(neg, -mag, mag), 0.0)
        comp = np.where(keep, comp >> np.uint64(10), comp)
    rest = np.clip(1.0 - np.sum(q * q, axis=1), 0.0, None)
    q[np.arange(q.shape[0]), largest] = np.sqrt(rest)
    return q


def encode_spz(gaussians: Gaussians) -> bytes:
    """The uncompressed SPZ v3 payload (header + blocks) of Gaussians given in the PLY's frame."""
    means, quats, scales, opacities, sh = checked_arrays(gaussians)
    n, k = means.shape[0], sh.shape[1]
    degree = {1: 0, 4: 1, 9: 2, 16: 3}[k]
    if n > MAX_POINTS:
        raise DlaInputError("gaussians", f"{n} Gaussians are more than an .spz holds here ({MAX_POINTS})")
    means, quats, sh = _flip_frame(means, quats, sh)
    fixed = np.sign(means) * np.floor(np.abs(means) * (1 << FRACTIONAL_BITS) + 0.5)  # [N, 3]
    if np.any(np.abs(fixed) > (1 << 23) - 1):
        raise DlaInputError(
            "gaussians.means",
            f"a position beyond +-{(1 << 23) / (1 << FRACTIONAL_BITS):.0f} m does not fit SPZ's 24-bit fixed point",
        )
    pos = fixed.astype(np.int64).astype("<i4").view(np.uint8).reshape(n, 3, 4)[:, :, :3]  # 24-bit two's complement
    alphas = to_u8(opacities * 255.0)
    colors = to_u8(sh[:, 0, :] * (COLOR_SCALE * 255.0) + 127.5)
    log_scales = np.log(scales)
    packed_scales = to_u8((log_scales + 10.0) * 16.0)
    rot = _pack_rotations(quats[:, [1, 2, 3, 0]])
    rest = to_u8(sh[:, 1:, :] * 128.0 + 128.0)  # [N, K - 1, 3]: coefficient-major, colour inner
    header = HEADER.pack(MAGIC, VERSION, n, degree, FRACTIONAL_BITS, 0, 0)
    blocks = (pos, alphas, colors, packed_scales, rot, rest)
    return header + b"".join(np.ascontiguousarray(b).tobytes() for b in blocks)


def write_spz(gaussians: Gaussians, path: str | os.PathLike, level: int = 6) -> None:
    """Write an SPZ v3 file (gzip, atomically) from Gaussians in the PLY's frame."""
    payload = encode_spz(gaussians)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(gzip.compress(payload, compresslevel=level, mtime=0))


def _gunzip(data: bytes, size: int, where) -> bytes:
    """The first `size` bytes (or fewer, if the stream ends) of a gzip stream: never more, so a
    small file claiming a huge payload costs no memory beyond what its header asks for."""
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        return d.decompress(data, size)
    except zlib.error as err:
        raise DlaInputError(where, f"not a valid gzip-compressed .spz ({err})") from None


def decode_spz(data: bytes, where: str | os.PathLike = "spz") -> dict:
    """A gzip-compressed SPZ (v2 or v3) -> dict of float64 arrays in the PLY's frame: means [N, 3],
    quats [N, 4] (w, x, y, z), scales [N, 3], opacities [N], sh [N, K, 3]; and version, degree."""
    if data[:4] == b"NGSP":
        raise DlaInputError(
            where,
            "is an SPZ version 4 file (zstd); dla reads versions 2 and 3 "
            "(convert with: splat-transform --spz-version 3 IN OUT.spz)",
        )
    if data[:2] != b"\x1f\x8b":
        raise DlaInputError(where, "not an .spz file (no gzip magic)")
    head = _gunzip(data, HEADER.size, where)[: HEADER.size]  # gzip streams decode from the front
    if len(head) < HEADER.size:
        raise DlaInputError(where, "truncated .spz header")
    magic, version, n, degree, frac, _flags, _ = HEADER.unpack(head)
    if magic != MAGIC:
        raise DlaInputError(where, "not an .spz file (no NGSP magic)")
    if version not in (2, 3):
        raise DlaInputError(where, f"SPZ version {version}; dla reads versions 2 and 3")
    if degree > 3:
        raise DlaInputError(where, f"SH degree {degree}; dla reads degrees 0-3")
    if n > MAX_POINTS:
        raise DlaInputError(where, f"header claims {n} Gaussians (at most {MAX_POINTS})")
    k = sh_coeffs_for_degree(degree)
    rot_bytes = 4 if version >= 3 else 3
    per = 9 + 1 + 3 + 3 + rot_bytes + 3 * (k - 1)
    body = _gunzip(data, HEADER.size + n * per, where)[HEADER.size :]  # extensions, if any, follow: ignored
    if len(body) < n * per:
        raise DlaInputError(where, f"truncated: {len(body)} bytes of data for {n} Gaussians that need {n * per}")
    at = 0

    def take(size: int) -> np.ndarray:
        nonlocal at
        block = np.frombuffer(body, dtype=np.uint8, count=size, offset=at)
        at += size
        return block

    raw = take(9 * n).reshape(n, 3, 3).astype(np.int64)
    fixed = raw[..., 0] | (raw[..., 1] << 8) | (raw[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)  # sign-extend 24 bits
    means = fixed / float(1 << frac)
    opacities = take(n) / 255.0
    colors = (take(3 * n).reshape(n, 3) / 255.0 - 0.5) / COLOR_SCALE
    scales = np.exp(take(3 * n).reshape(n, 3) / 16.0 - 10.0)
    if version >= 3:
        xyzw = _unpack_rotations(take(4 * n).reshape(n, 4))
    else:
        xyz = take(3 * n).reshape(n, 3) / 127.5 - 1.0
        xyzw = np.concatenate([xyz, np.sqrt(np.clip(1.0 - np.sum(xyz**2, axis=1, keepdims=True), 0, None))], axis=1)
    quats = xyzw[:, [3, 0, 1, 2]]
    quats = quats / np.linalg.norm(quats, axis=1, keepdims=True)  # v2: |xyz| may round past 1 (w = 0)
    rest = (take(3 * (k - 1) * n).reshape(n, k - 1, 3) - 128.0) / 128.0
    sh = np.concatenate([colors[:, None, :], rest], axis=1)
    means, quats, sh = _flip_frame(means, quats, sh)
    return {
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": opacities,
        "sh": sh,
        "version": version,
        "degree": degree,
    }


def read_spz(path: str | os.PathLike) -> Gaussians:
    """Read an .spz (v2/v3) into activated float32 Gaussians in the PLY's frame."""
    import torch

    from dlacli.io.files import read_bytes

    a = decode_spz(read_bytes(path), path)
    t = [
        torch.from_numpy(np.ascontiguousarray(a[k], dtype=np.float32))
        for k in ("means", "quats", "scales", "opacities", "sh")
    ]
    return Gaussians(*t)


def summarize_spz(path: str | os.PathLike) -> dict:
    """JSON-able summary of an .spz (used by `dla info`), values in the PLY's frame."""
    from dlacli.io.files import read_bytes
    from dlacli.io.ply import gaussian_stats

    a = decode_spz(read_bytes(path), path)
    return {
        "kind": "gaussians.spz",
        "format": f"spz v{a['version']} (Niantic)",
        **gaussian_stats(a["means"], a["scales"], a["opacities"], int(a["degree"])),
    }
