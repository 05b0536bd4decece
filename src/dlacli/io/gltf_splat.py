"""glTF 2.0 binary (.glb) with KHR_gaussian_splatting (formats/gltf-splat.md).

One scene, one node, one mesh with one primitive of mode POINTS (0) whose attributes are, per
Gaussian: POSITION (float VEC3, with min/max), KHR_gaussian_splatting:ROTATION (float VEC4, unit
quaternion in glTF's x, y, z, w order), KHR_gaussian_splatting:SCALE (float VEC3, linear standard
deviations), KHR_gaussian_splatting:OPACITY (float SCALAR in [0, 1]),
KHR_gaussian_splatting:SH_DEGREE_0_COEF_0 (float VEC3, the DC coefficient: rgb = 0.5 + SH_C0 c),
SH_DEGREE_l_COEF_n for degrees 1..3 when present, and COLOR_0 (normalised unsigned byte VEC4:
the clamped DC colour decoded from sRGB to linear, alpha = opacity) as the point-cloud fallback the
spec recommends. The extension object says kernel "ellipse", colorSpace "srgb_rec709_display".

glTF is +Y up with the asset's front towards +Z; the writer takes Gaussians already in those
axes (the export stage rotates them, docs/export.md).
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.io.atomic import atomic_path
from dlacli.io.splat import checked_arrays, to_u8
from dlacli.types import SH_C0, Gaussians, sh_degree_for_coeffs, srgb_to_linear

EXTENSION = "KHR_gaussian_splatting"
FLOAT, UNSIGNED_BYTE = 5126, 5121
ARRAY_BUFFER = 34962
POINTS = 0
GLB_MAGIC, GLB_VERSION = 0x46546C67, 2  # "glTF"
CHUNK_JSON, CHUNK_BIN = 0x4E4F534A, 0x004E4942
MAX_BYTES = (1 << 32) - 1  # a GLB's length field is a uint32


def sh_attribute_names(degree: int) -> list[str]:
    """Attribute semantics of the SH coefficients, index k = 0..(degree+1)^2 - 1 in 3DGS order."""
    names = [f"{EXTENSION}:SH_DEGREE_0_COEF_0"]
    for level in range(1, degree + 1):
        names += [f"{EXTENSION}:SH_DEGREE_{level}_COEF_{n}" for n in range(2 * level + 1)]
    return names


def encode_glb(gaussians: Gaussians, generator: str = "dla") -> bytes:
    """The .glb bytes of Gaussians given in glTF's axes (+Y up, front +Z)."""
    means, quats, scales, opacities, sh = checked_arrays(gaussians)
    n = means.shape[0]
    if n == 0:
        raise DlaInputError("gaussians", "a glTF accessor needs at least one Gaussian")
    rgb = np.clip(0.5 + SH_C0 * sh[:, 0, :], 0.0, 1.0)
    columns: list[tuple[str, np.ndarray, str, int, bool]] = [
        ("POSITION", means.astype("<f4"), "VEC3", FLOAT, False),
        (
            "COLOR_0",
            to_u8(np.concatenate([srgb_to_linear(rgb), opacities[:, None]], axis=1) * 255.0),
            "VEC4",
            UNSIGNED_BYTE,
            True,
        ),
        (f"{EXTENSION}:ROTATION", quats[:, [1, 2, 3, 0]].astype("<f4"), "VEC4", FLOAT, False),
        (f"{EXTENSION}:SCALE", scales.astype("<f4"), "VEC3", FLOAT, False),
        (f"{EXTENSION}:OPACITY", opacities.astype("<f4"), "SCALAR", FLOAT, False),
    ]
    degree = sh_degree_for_coeffs(sh.shape[1])
    for k, name in enumerate(sh_attribute_names(degree)):
        columns.append((name, sh[:, k, :].astype("<f4"), "VEC3", FLOAT, False))
    if not all(np.all(np.isfinite(c[1])) for c in columns if c[3] == FLOAT):
        raise DlaInputError("gaussians", "a value is outside float32's range")

    blobs, views, accessors, attributes, offset = [], [], [], {}, 0
    for index, (name, data, kind, component, normalized) in enumerate(columns):
        raw = np.ascontiguousarray(data).tobytes()
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(raw), "target": ARRAY_BUFFER})
        accessor = {"bufferView": index, "componentType": component, "count": n, "type": kind}
        if normalized:
            accessor["normalized"] = True
        if name == "POSITION":  # required for POSITION by the glTF spec
            accessor["min"] = [float(v) for v in data.min(axis=0)]
            accessor["max"] = [float(v) for v in data.max(axis=0)]
        accessors.append(accessor)
        attributes[name] = index
        pad = (-len(raw)) % 4  # every view starts on a 4-byte boundary
        blobs.append(raw + b"\0" * pad)
        offset += len(raw) + pad
    doc = {
        "asset": {"version": "2.0", "generator": generator},
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "avatar"}],
        "meshes": [
            {
                "name": "avatar",
                "primitives": [
                    {
                        "attributes": attributes,
                        "mode": POINTS,
                        "extensions": {
                            EXTENSION: {
                                "kernel": "ellipse",
                                "colorSpace": "srgb_rec709_display",
                                "projection": "perspective",
                                "sortingMethod": "cameraDistance",
                            }
                        },
                    }
                ],
            }
        ],
        "buffers": [{"byteLength": offset}],
        "bufferViews": views,
        "accessors": accessors,
    }
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * ((-len(text)) % 4)
    total = 12 + 8 + len(text) + 8 + offset
    if total > MAX_BYTES:
        raise DlaInputError(
            "gaussians", f"{n} Gaussians make a {total / 2**30:.1f} GiB .glb; the format holds at most 4 GiB"
        )
    return b"".join(
        [
            struct.pack("<III", GLB_MAGIC, GLB_VERSION, total),
            struct.pack("<II", len(text), CHUNK_JSON),
            text,
            struct.pack("<II", offset, CHUNK_BIN),
            *blobs,
        ]
    )


def write_glb(gaussians: Gaussians, path: str | os.PathLike) -> None:
    """Write a KHR_gaussian_splatting .glb (atomically); Gaussians in glTF's axes."""
    data = encode_glb(gaussians)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)
