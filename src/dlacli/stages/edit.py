"""Edit and blend avatars in the UV-aligned latent space (docs/architecture.md "The method", Edit and interp).

Because the avatar code Z is aligned with the body's UV space, a body region is a set of texels of
Z: `swap_region` takes those texels from another avatar, `interpolate` blends two codes. Both are
plain functions on `dlacli.types.Avatar`; the CLI commands `dla edit swap` and `dla interp` wrap them.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt

from dlacli.errors import DlaInputError
from dlacli.types import PHENOTYPE_KEYS, Avatar, BodyParams


def check_compatible(a: Avatar, b: Avatar, where_a: str = "A", where_b: str = "B") -> None:
    """Raise DlaInputError unless `a` and `b` live in the same latent space (layout, encoder,
    decoder, checkpoint and Z shape all equal)."""
    for attr in ("uv_layout", "encoder", "decoder", "checkpoint"):
        va, vb = getattr(a, attr), getattr(b, attr)
        if va != vb:
            raise DlaInputError(
                where_b,
                f"{attr} {vb!r} differs from {where_a}'s {va!r}: avatars must come from the same "
                "encoder, decoder and UV layout to be edited together",
            )
    if a.z.shape != b.z.shape:
        raise DlaInputError(where_b, f"z has shape {b.z.shape}, {where_a}'s has {a.z.shape}")


def feathered_weight(mask: np.ndarray, feather: float) -> np.ndarray:
    """[H, W] float32 blend weight: 1 inside `mask` [H, W] bool, falling linearly to 0 over
    `feather` texels outside it (texels farther than `feather` from the region keep weight 0)."""
    if feather < 0:
        raise DlaInputError("--feather", f"must be >= 0, got {feather}")
    if feather == 0 or not mask.any():
        return mask.astype(np.float32)
    outside = distance_transform_edt(~mask)  # distance in texels to the nearest region texel
    return np.clip(1.0 - outside / (feather + 1.0), 0.0, 1.0).astype(np.float32)


def _blend_maps(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(1 - w) a + w b on [C, H, W] maps with a weight [H, W]; exact where w is 0 or 1."""
    out = a.astype(np.float32, copy=True)
    sel = w > 0
    ws = w[sel]
    out[:, sel] = (1.0 - ws) * a[:, sel] + ws * b[:, sel]
    return out


def _region_weight(region: str, shape: tuple[int, int], feather: float, where: str = "avatar") -> np.ndarray:
    from dlacli.body.regions import region_mask

    h, w = shape
    if h != w:
        raise DlaInputError(where, f"z is {h}x{w}; region masks need a square UV map")
    return feathered_weight(region_mask(region, h), feather)


def swap_region(
    a: Avatar, b: Avatar, region: str, feather: float = 0.0, where_a: str = "A", where_b: str = "B"
) -> Avatar:
    """Avatar `a` with the texels of `region` (see dlacli.body.regions.REGION_NAMES) taken from `b`.

    The body (shape and pose) stays `a`'s. `feather` (texels at Z's resolution) blends linearly
    across that many texels outside the region; texels farther away are exactly `a`'s.
    The result is re-decoded from its z: a cached canonical map is dropped, except for a decoder
    that is linear in z (identity), whose maps swap exactly like z when both avatars have one of
    the same size.
    """
    from dlacli.avatar.codec import is_linear, same_space

    a, b = same_space(a, b)
    check_compatible(a, b, where_a, where_b)
    z = _blend_maps(a.z, b.z, _region_weight(region, a.z.shape[1:], feather, where_a))
    canonical = None
    if is_linear(a) and a.canonical is not None and b.canonical is not None and a.canonical.shape == b.canonical.shape:
        scale = a.canonical.shape[1] / a.z.shape[1]
        w = _region_weight(region, a.canonical.shape[1:], feather * scale, where_a)
        canonical = _blend_maps(a.canonical, b.canonical, w)
    edits = list(a.extra.get("edits", [])) + [{"op": "swap", "region": region, "feather": feather}]
    return Avatar(
        z=z,
        encoder=a.encoder,
        decoder=a.decoder,
        body=a.body,
        uv_layout=a.uv_layout,
        checkpoint=a.checkpoint,
        canonical=canonical,
        extra={**a.extra, "edits": edits},
    )


def _lerp(a, b, t: float):
    return (1.0 - t) * np.asarray(a, dtype=np.float64) + t * np.asarray(b, dtype=np.float64)


def _slerp_axis_angle(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    """Rotation-vector interpolation along the shortest arc; exact at t = 0 and t = 1."""
    if t == 0.0:
        return np.array(a, dtype=np.float64)
    if t == 1.0:
        return np.array(b, dtype=np.float64)
    import torch

    from dlacli.geometry import (
        axis_angle_to_quat,
        quat_conjugate,
        quat_multiply,
        quat_to_axis_angle,
    )

    qa = axis_angle_to_quat(torch.as_tensor(a, dtype=torch.float64))
    qb = axis_angle_to_quat(torch.as_tensor(b, dtype=torch.float64))
    delta = quat_to_axis_angle(quat_multiply(quat_conjugate(qa), qb))  # shortest-arc relative turn
    q = quat_multiply(qa, axis_angle_to_quat(delta * t))
    return quat_to_axis_angle(q).numpy()


def interpolate_body(a: BodyParams, b: BodyParams, t: float) -> BodyParams:
    """Phenotype and root translation linearly, rotations along the shortest arc."""
    bones = sorted(set(a.pose) | set(b.pose))
    zero = np.zeros(3)
    return BodyParams(
        phenotype={k: float(_lerp(a.phenotype[k], b.phenotype[k], t)) for k in PHENOTYPE_KEYS},
        root_rotation=_slerp_axis_angle(a.root_rotation, b.root_rotation, t),
        root_translation=_lerp(a.root_translation, b.root_translation, t),
        pose={k: _slerp_axis_angle(a.pose.get(k, zero), b.pose.get(k, zero), t) for k in bones},
        model=a.model,
    )


def interpolate(a: Avatar, b: Avatar, t: float, where_a: str = "A", where_b: str = "B") -> Avatar:
    """The avatar a fraction `t` of the way from `a` to `b`: z = (1 - t) z_a + t z_b.

    t = 0 and t = 1 reproduce `a` and `b` exactly (z, body and cached canonical map); t outside
    [0, 1] extrapolates. Between them the blend is re-decoded from z: the canonical cache is
    dropped, except for a decoder linear in z (identity), where it blends like z.
    """
    from dlacli.avatar.codec import is_linear, same_space

    a, b = same_space(a, b)
    check_compatible(a, b, where_a, where_b)
    t = float(t)
    if not np.isfinite(t):
        raise DlaInputError("--t", f"must be a finite number, got {t}")
    z = ((1.0 - t) * a.z + t * b.z).astype(np.float32)
    canonical = {0.0: a.canonical, 1.0: b.canonical}.get(t)
    if (
        canonical is None
        and is_linear(a)
        and a.canonical is not None
        and b.canonical is not None
        and a.canonical.shape == b.canonical.shape
    ):
        canonical = ((1.0 - t) * a.canonical + t * b.canonical).astype(np.float32)
    base = a if t < 0.5 else b
    return Avatar(
        z=z,
        encoder=a.encoder,
        decoder=a.decoder,
        body=interpolate_body(a.body, b.body, t),
        uv_layout=a.uv_layout,
        checkpoint=a.checkpoint,
        canonical=canonical,
        extra=dict(base.extra),
    )
