"""The codec: the one place that maps an avatar's `encoder` / `decoder` / `checkpoint` to code.

Method (docs/architecture.md, "The method" and "The codec"): the Gaussian Parameter Decoder turns
the latent Z into the UV Gaussian map F = F_c(Z) + F_delta(Z, pose maps, Plücker rays). F_c is the
canonical part, computed once per avatar (and cacheable in avatar.npz); F_delta depends on the
target pose and, for a view-conditioned decoder, on the camera. Callers never test method names: `Decoded` asks
the decoder what it needs (`pose_conditioned`, `view_conditioned`, `linear`) and calls
`canonical` once and `delta` per frame (and per camera when view-conditioned); the one path from
a Decoded avatar to posed Gaussians is avatar/posed.py.

The non-learned pair is one implementation of the same interface: encoder "unproject" (mesh
unprojection, stages/lift/unproject.py) and decoder "identity" (F = Z: no delta, no checkpoint, linear).
A decoder without weights is known by name (`_DECODERS`: identity and view-cosine; a new one joins
with `register_decoder`, as the tests' toy decoders do); a learned decoder is not registered but
found through the checkpoint hash its avatars record (the checkpoint resolver rebuilds it).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.types import Avatar


class PoseConditioning:
    """What a pose-conditioned decoder sees of one target pose, as UV maps [3, R, R]:
    `relative_positions` (posed minus rest positions, metres) and `normals` (unit normals of the
    posed body). Given as tensors, or (`of_body`) computed from the posed vertices when first
    read, so a decoder pays only for the maps it reads; `positions` (the posed texel positions
    [R, R, 3], channels last) is what the rays from a camera to the body share with them."""

    def __init__(self, relative_positions: torch.Tensor | None = None, normals: torch.Tensor | None = None):
        self._maps: dict[str, torch.Tensor | None] = {"relative_positions": relative_positions, "normals": normals}
        self._body: tuple | None = None  # (vertices [V, 3], rest vertices () -> [V, 3], R) for `of_body`

    @classmethod
    def of_body(cls, vertices: torch.Tensor, rest_vertices: Callable[[], np.ndarray], resolution: int):
        """The maps of posed vertices [V, 3] at resolution R, each computed when first read;
        rest_vertices() gives the zero-pose vertices [V, 3] (asked for only by the relative
        positions)."""
        out = cls()
        out._body = (vertices, rest_vertices, resolution)
        return out

    def _surface(self) -> None:
        from dlacli.body.uv import surface_maps

        vertices, _, resolution = self._body
        pos, nrm = surface_maps(vertices, resolution)  # [R, R, 3] each
        self._maps["positions"] = pos
        if self._maps["normals"] is None:
            self._maps["normals"] = nrm.permute(2, 0, 1).contiguous()

    @property
    def relative_positions(self) -> torch.Tensor:
        if self._maps["relative_positions"] is None and self._body is not None:
            from dlacli.body.uv import relative_position_map

            vertices, rest, resolution = self._body
            rel = relative_position_map(vertices, rest(), resolution)  # [R, R, 3]
            self._maps["relative_positions"] = rel.permute(2, 0, 1).contiguous()
        return self._maps["relative_positions"]

    @property
    def normals(self) -> torch.Tensor:
        if self._maps["normals"] is None and self._body is not None:
            self._surface()
        return self._maps["normals"]

    @property
    def positions(self) -> torch.Tensor | None:
        """The posed texel positions [R, R, 3] of `of_body` (None for maps given as tensors)."""
        if self._body is None:
            return None
        if "positions" not in self._maps:
            self._surface()
        return self._maps["positions"]


class Decoder:
    """Z -> F. Subclasses set the flags and override `canonical` and, if conditioned, `delta`."""

    name = "base"
    pose_conditioned = False  # delta depends on the target pose
    view_conditioned = False  # delta depends on the camera's rays
    linear = False  # F is linear in Z: maps decoded from blended Zs may be blended directly
    delta_geometry = True  # F_delta may move offsets, rotations or scales; False: opacity and colour only
    resolution: int | None = None  # the resolution of the UV maps `delta` wants (pose, rays)

    def canonical(self, z: torch.Tensor) -> torch.Tensor:
        """F_c [14, R, R] from z [C, H, W]."""
        raise NotImplementedError

    def delta(self, z: torch.Tensor, pose: PoseConditioning | None, rays: torch.Tensor | None) -> torch.Tensor | None:
        """F_delta [14, R, R] for one pose (None unless pose_conditioned) and one camera's UV ray
        map [6, R, R] (None unless view_conditioned); None means zero."""
        return None

    def prepare(self, z: torch.Tensor):
        """What `canonical` and every `delta` of one z share (a network's trunk), computed once per
        `Decoded` and handed back to them as the keyword `prepared`; None (the default): nothing
        is shared and they are called without it."""
        return None

    @property
    def conditioned(self) -> bool:
        return self.pose_conditioned or self.view_conditioned


class IdentityDecoder(Decoder):
    """F = Z (the Gaussian map is the code itself): no delta, no weights."""

    name = "identity"
    linear = True

    def __init__(self, checkpoint: str = "", where: str = "avatar"):
        if checkpoint:
            raise DlaInputError(where, f"the identity decoder takes no checkpoint, found {checkpoint!r}")
        self.where = where

    def canonical(self, z: torch.Tensor) -> torch.Tensor:
        from dlacli.avatar.gaussian_map import CHANNELS

        if z.shape[0] != CHANNELS:
            raise DlaInputError(self.where, f"identity decoder needs z with {CHANNELS} channels, got {tuple(z.shape)}")
        return z


class ViewCosineDecoder(IdentityDecoder):
    """The identity decoder plus view-dependent colour with one falloff per texel:
    z [15, R, R] = F_c (the 14 channels of F, colour as seen head-on) and, in channel 14, the
    falloff k. Seen from a camera, a texel's colour is rgb (1 - k + k cos), cos = the angle
    between the posed body's normal there and the direction to the camera, clamped to [0, 1]:
    F_delta holds rgb k (cos - 1) in the colour channels and zeros elsewhere. k = 0 is the
    identity decoder; k > 0 darkens surfaces seen obliquely (a light near the camera, a rough
    material's falloff), k < 0 brightens them. `dla lift` measures k from the views
    (stages/lift/bake.py `view_falloff`) and writes this decoder only when it is not ~0."""

    name = "view-cosine"
    pose_conditioned = True  # the posed normals
    view_conditioned = True  # the rays
    linear = True  # F_c = z[:14]; F_delta is not linear in z (rgb times k)
    delta_geometry = False  # colour only
    FALLOFF = 14  # z's channel of k

    def canonical(self, z: torch.Tensor) -> torch.Tensor:
        from dlacli.avatar.gaussian_map import CHANNELS

        if z.shape[0] != CHANNELS + 1:
            raise DlaInputError(
                self.where, f"view-cosine decoder needs z with {CHANNELS + 1} channels, got {tuple(z.shape)}"
            )
        return z[:CHANNELS]

    def delta(self, z: torch.Tensor, pose: PoseConditioning | None, rays: torch.Tensor | None) -> torch.Tensor | None:
        from dlacli.avatar.gaussian_map import CHANNELS, RGB
        from dlacli.kernel_path import takes_kernels

        if pose is None or rays is None:
            return None
        normals, rays = pose.normals.to(z), rays.to(z)
        out = torch.zeros((CHANNELS, *z.shape[1:]), dtype=z.dtype, device=z.device)
        if takes_kernels(z, normals, rays):  # numba, the same float32 steps
            from dlacli.avatar.ray_kernels import view_cosine_rgb

            arrays = (z[RGB], z[self.FALLOFF], normals, rays)
            view_cosine_rgb(*(a.contiguous().numpy() for a in arrays), out[RGB].numpy())
            return out
        out[RGB] = z[RGB] * (shading(z[self.FALLOFF], view_cosine(normals, rays)) - 1.0)
        return out


def same_space(a: Avatar, b: Avatar) -> tuple[Avatar, Avatar]:
    """`a` and `b` in one latent space where one embeds in the other: an identity avatar is a
    view-cosine one with falloff 0, so with one of each the identity one gains the falloff
    channel (zeros). Anything else is returned as it is (edits' `check_compatible` judges)."""
    from dataclasses import replace

    def promote(x: Avatar) -> Avatar:
        k = np.zeros((1, *x.z.shape[1:]), np.float32)
        return replace(x, z=np.concatenate([x.z.astype(np.float32), k]), decoder=ViewCosineDecoder.name, canonical=None)

    if (
        {a.decoder, b.decoder} == {ViewCosineDecoder.name, IdentityDecoder.name}
        and not a.checkpoint
        and not b.checkpoint
    ):
        return (promote(a), b) if a.decoder == IdentityDecoder.name else (a, promote(b))
    return a, b


def shading(falloff, cosine):
    """The view-cosine decoder's colour factor 1 - k + k cos, cos clamped to [0, 1] (numpy arrays
    or torch tensors; stages/lift/unproject.py bakes and measures k with the same law)."""
    return 1.0 - falloff + falloff * cosine.clip(0.0, 1.0)


def view_cosine(normals: torch.Tensor, rays: torch.Tensor) -> torch.Tensor:
    """cos of the angle between unit normals [3, ...] and the direction back along rays [6, ...]
    (Plücker, unit direction first) toward the camera, clamped to [0, 1] -> [...]. UV maps
    ([3, R, R], [6, R, R]) without a gradient on the CPU in float32: a numba kernel with the same
    float32 steps (`ray_kernels.view_cosine_map`; to float32 rounding, as torch's sqrt is not
    correctly rounded), the one every decoder's no-gradient F_delta reads."""
    from dlacli.geometry import vector_norm
    from dlacli.kernel_path import takes_kernels

    if normals.ndim == 3 and rays.ndim == 3 and takes_kernels(normals, rays):
        from dlacli.avatar.ray_kernels import view_cosine_map

        out = torch.empty(normals.shape[1:], dtype=normals.dtype)
        view_cosine_map(normals.contiguous().numpy(), rays.contiguous().numpy(), out.numpy())
        return out
    d = rays[:3] / vector_norm(rays[:3], dim=0).clamp_min(1e-12)
    return (-(normals * d).sum(dim=0)).clamp(0.0, 1.0)


# name -> factory(checkpoint, where) -> Decoder
_DECODERS: dict[str, Callable[[str, str], Decoder]] = {"identity": IdentityDecoder, "view-cosine": ViewCosineDecoder}


def register_decoder(name: str, factory: Callable[[str, str], Decoder]) -> None:
    """Make `factory(checkpoint, where)` the decoder for avatars whose `decoder` is `name`."""
    _DECODERS[name] = factory


def decoder_names() -> list[str]:
    return sorted(_DECODERS)


def is_linear(avatar: Avatar) -> bool:
    """Whether the avatar's decoder is linear in Z (so its canonical maps may be blended like Z);
    False for a decoder this version does not know."""
    factory = _DECODERS.get(avatar.decoder)
    return bool(factory is not None and getattr(factory, "linear", False))


def resolve_decoder(avatar: Avatar, where: str = "avatar", checkpoint: str | None = None) -> Decoder:
    """The decoder an avatar names, built with its checkpoint (`checkpoint`: a path that
    overrides the hash's lookup, i.e. `--checkpoint PATH`); one-line error if unknown.

    A registered name is built by its factory. Otherwise, an avatar with a checkpoint hash is
    decoded by the network in that checkpoint (resolved in the checkpoints cache or at
    `checkpoint`, avatar/checkpoint.py), which must be a Decoder of that name."""
    factory = _DECODERS.get(avatar.decoder)
    if factory is not None:
        return factory(checkpoint or avatar.checkpoint, checkpoint or where)
    if not avatar.checkpoint:
        raise DlaInputError(
            where, f"decoder {avatar.decoder!r} is not available in this version (known: {', '.join(decoder_names())})"
        )
    from dlacli.avatar.checkpoint import load_checkpoint, resolve_checkpoint

    path = resolve_checkpoint(checkpoint or avatar.checkpoint)
    loaded = load_checkpoint(path)
    if checkpoint is not None and loaded.hash != avatar.checkpoint:
        raise DlaInputError(
            checkpoint, f"holds weights {loaded.hash[:16]}, but {where} was made with {avatar.checkpoint[:16]}"
        )
    net = loaded.module
    if not isinstance(net, Decoder) or getattr(net, "name", None) != avatar.decoder:
        raise DlaInputError(path, f"holds a {type(net).__name__}, not the {avatar.decoder!r} decoder {where} names")
    return net


def pose_conditioning(vertices: torch.Tensor, rest_vertices: np.ndarray, resolution: int) -> PoseConditioning:
    """The UV maps a pose-conditioned decoder sees for posed vertices [V, 3] of a body whose
    zero-pose vertices are rest_vertices [V, 3] (each computed when first read)."""
    return PoseConditioning.of_body(vertices, lambda: rest_vertices, resolution)


def uv_rays(vertices: torch.Tensor, eye: torch.Tensor, resolution: int, positions: torch.Tensor | None = None):
    """Plücker rays [6, R, R] from a camera centre eye [3] to each texel's point on the posed
    body vertices [V, 3] (what a view-conditioned decoder sees of a camera); `positions`: the
    body's `position_map` at R, when already made."""
    from dlacli.body.uv import position_map
    from dlacli.geometry import plucker_rays_uv
    from dlacli.kernel_path import takes_kernels

    pos = position_map(vertices, resolution) if positions is None else positions  # [R, R, 3]
    eye = torch.as_tensor(eye, dtype=pos.dtype, device=pos.device)
    if takes_kernels(pos, eye):  # numba, the same float32 steps
        from dlacli.avatar.ray_kernels import uv_plucker

        out = torch.empty((6, *pos.shape[:2]), dtype=pos.dtype)
        uv_plucker(pos.contiguous().numpy(), eye.contiguous().numpy(), out.numpy())
        return out
    return plucker_rays_uv(pos, eye).permute(2, 0, 1).contiguous()


class Decoded:
    """An avatar's decoder with its canonical map computed once: `at(pose, rays)` gives F.

    A stored canonical map is used as the cache of F_c only for a non-linear decoder (for a
    linear one, e.g. identity, F_c is recomputed: it costs nothing and cannot be stale)."""

    def __init__(self, avatar: Avatar, where: str = "avatar", checkpoint: str | None = None):
        from dlacli.body.uv import UV_LAYOUT

        if avatar.uv_layout != UV_LAYOUT:
            raise DlaInputError(
                where, f"uv_layout {avatar.uv_layout!r} is not one this version decodes ({UV_LAYOUT!r})"
            )
        decoder = resolve_decoder(avatar, where, checkpoint)
        f_c = None
        if avatar.canonical is not None and not decoder.linear:
            f_c = torch.from_numpy(np.ascontiguousarray(avatar.canonical, dtype=np.float32))
        z = torch.from_numpy(np.ascontiguousarray(avatar.z, dtype=np.float32))
        self._bind(decoder, z, f_c, dict(avatar.body.phenotype), None)

    @classmethod
    def of(cls, decoder: Decoder, z: torch.Tensor, rest_vertices=None, phenotype: dict | None = None) -> Decoded:
        """A code z [C, H, W] that is no avatar file (yet): one being refined or trained (z may
        require grad; F_c and every F is differentiable in it). The body's zero-pose vertices
        rest_vertices [V, 3] (or its phenotype, to compute them) serve pose conditioning."""
        out = cls.__new__(cls)
        out._bind(decoder, z, None, dict(phenotype or {}), rest_vertices)
        return out

    def _bind(self, decoder: Decoder, z: torch.Tensor, f_c: torch.Tensor | None, phenotype: dict, rest) -> None:
        self.decoder, self.z, self.phenotype = decoder, z, phenotype
        self._rest: np.ndarray | None = None if rest is None else np.asarray(rest)
        self._prepared: tuple | None = None  # (decoder.prepare(z),) once asked for
        self.f_c = f_c if f_c is not None else decoder.canonical(z, **self._shared())
        self._sampled: tuple | None = None  # (samples, F_c's version, gaussian_map.sampled_params)

    def sampled_canonical(self, samples) -> tuple | None:
        """`gaussian_map.sampled_params(f_c, samples)`, kept for the last samples asked for, or
        None while F_c can change or carry gradients (a code being refined): F_c does not depend
        on the pose, so posing an avatar frame after frame looks it up once."""
        from dlacli.avatar.gaussian_map import sampled_params

        if self.f_c.requires_grad or self.z.requires_grad:
            return None
        version = (self.f_c._version, self.z._version)
        if self._sampled is None or self._sampled[0] is not samples or self._sampled[1] != version:
            with torch.no_grad():
                kept = tuple(x.contiguous() for x in sampled_params(self.f_c, samples))  # as the kernels read them
                self._sampled = (samples, version, kept)
        return self._sampled[2]

    def _shared(self) -> dict:
        """The keyword arguments `canonical` / `delta` take: what `prepare` shared, if anything."""
        if self._prepared is None:
            self._prepared = (self.decoder.prepare(self.z),)
        return {} if self._prepared[0] is None else {"prepared": self._prepared[0]}

    @property
    def conditioned(self) -> bool:
        return self.decoder.conditioned

    @property
    def resolution(self) -> int:
        return self.decoder.resolution or int(self.f_c.shape[-1])

    def pose(self, vertices: torch.Tensor) -> PoseConditioning | None:
        """Pose conditioning for posed vertices [V, 3], or None when the decoder needs none."""
        if not self.decoder.pose_conditioned:
            return None
        return PoseConditioning.of_body(vertices, self._rest_vertices, self.resolution)

    def _rest_vertices(self) -> np.ndarray:
        if self._rest is None:
            from dlacli.body.model import get_body_model

            self._rest = get_body_model().rest_vertices(self.phenotype)
        return self._rest

    def rays(self, vertices: torch.Tensor, eye, pose: PoseConditioning | None = None) -> torch.Tensor | None:
        """UV rays from camera centre eye [3] for posed vertices [V, 3], or None when the
        decoder is not view-conditioned; `pose`: these vertices' `pose`, whose texel positions
        the rays then share."""
        if not self.decoder.view_conditioned:
            return None
        positions = None if pose is None else pose.positions
        if positions is not None and positions.shape[0] != self.resolution:
            positions = None
        return uv_rays(vertices, eye, self.resolution, positions)

    def delta(self, pose: PoseConditioning | None = None, rays: torch.Tensor | None = None) -> torch.Tensor | None:
        """F_delta [14, R, R] for a pose and a camera's UV rays (each passed on only when the
        decoder is conditioned on it); None for an unconditioned decoder, or a zero delta."""
        if not self.decoder.conditioned:
            return None
        pose = pose if self.decoder.pose_conditioned else None
        rays = rays if self.decoder.view_conditioned else None
        return self.decoder.delta(self.z, pose, rays, **self._shared())

    def at(self, pose: PoseConditioning | None = None, rays: torch.Tensor | None = None) -> torch.Tensor:
        """F [14, R, R] = F_c + F_delta(pose, rays); F_c itself for an unconditioned decoder."""
        d = self.delta(pose, rays)
        return self.f_c if d is None else self.f_c + d
