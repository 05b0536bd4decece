"""The UV Gaussian map F and the Gaussians drawn from it (docs/architecture.md "The method", Animate).

F is a [14, R, R] map over the body's UV space (docs/conventions.md "UV space"), CHANNELS channels
(the slices OPACITY, RGB, OFFSET, ROTATION, LOG_SCALE below, defined once in dlacli.types):

    0       opacity, as a logit
    1..3    colour, rgb (rendered clamped to [0, 1])
    4..6    position offset dxyz in the texel's tangent frame, metres
    7..10   rotation dR in the tangent frame, quaternion (w, x, y, z), normalised at use
    11..13  log of the scale multiplier ds (texel units: ds = 1 is about one texel of a 256 map)

Gaussians are sampled from F at fixed surface samples (half uniform in UV, half uniform on the
mesh surface, as in the paper) by bilinear lookup, then placed with the posed body's tangent frames:
x = T + R dxyz, R_g = R dR, s = S ds (dlacli.body.skinning). Which map F an avatar gives (the
identity decoder's F = Z, or a learned GPD's F_c + F_delta) is the codec's business
(dlacli.avatar.codec); this module only samples and places a given F.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as nnf

from dlacli.errors import DlaInputError
from dlacli.geometry import vector_norm
from dlacli.kernel_path import takes_kernels
from dlacli.limits import DEFAULT_GAUSSIANS, MIN_GAUSSIANS
from dlacli.types import F_CHANNELS, F_LOG_SCALE, F_OFFSET, F_OPACITY, F_RGB, F_ROTATION, Gaussians

# F's channel layout, defined once in dlacli.types (io/avatar.py checks files with it), by the names used above io/
CHANNELS, OPACITY, RGB, OFFSET, ROTATION, LOG_SCALE = F_CHANNELS, F_OPACITY, F_RGB, F_OFFSET, F_ROTATION, F_LOG_SCALE


@dataclass(frozen=True)
class Samples:
    """Fixed surface sample points that carry one Gaussian each (numpy; `lookup` and
    `sample_frames` move them to the device and dtype of the map or vertices they meet).
    `make_samples` hands the same object to every caller asking for the same set: read only."""

    face_id: np.ndarray  # [N] int64 triangle of the body mesh
    bary: np.ndarray  # [N, 3] float32 barycentrics
    uv: np.ndarray  # [N, 2] float32 UV coordinates (u right, v up)

    def __len__(self) -> int:
        return self.face_id.shape[0]


def make_samples(n: int = DEFAULT_GAUSSIANS, seed: int = 0) -> Samples:
    """`_make_samples`, the last few sets kept (drawing 131,072 takes about 50 ms; a render, an
    animation and a refinement each ask for theirs again)."""
    if n < MIN_GAUSSIANS:
        raise DlaInputError("--gaussians", f"needs at least {MIN_GAUSSIANS} Gaussians, got {n}")
    return _make_samples(int(n), int(seed))


@functools.lru_cache(maxsize=2)
def _make_samples(n: int, seed: int) -> Samples:
    """n samples: n // 2 uniform over the covered UV texels, the rest uniform by surface area,
    ordered by face (a stable sort): samples next to each other in memory lie next to each
    other on the body, so the skinning kernels' per-sample gathers of face and vertex data stay
    in cache (the posing of 131,072 Gaussians took about a quarter longer in draw order)."""
    from dlacli.body.uv import sample_surface, sample_uv, sample_uv_points

    f_uv, b_uv = sample_uv(n // 2, seed=seed)
    f_s, b_s = sample_surface(n - n // 2, seed=seed + 1)
    face_id = np.concatenate([f_uv, f_s])
    bary = np.concatenate([b_uv, b_s]).astype(np.float32)
    order = np.argsort(face_id, kind="stable")
    face_id, bary = face_id[order], np.ascontiguousarray(bary[order])
    return Samples(face_id, bary, sample_uv_points(face_id, bary).astype(np.float32))


def lookup(fmap: torch.Tensor, uv: np.ndarray | torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of maps [B..., C, R, R] at UV points [N, 2] -> [B..., N, C]
    (differentiable in fmap; the points move to fmap's device and dtype).

    Texel centres follow docs/conventions.md: u = (j + 0.5) / R, v = 1 - (i + 0.5) / R.
    Points given as a numpy array are taken as fixed: where they fall in the map is kept while
    the array lives (`_kept`), so do not write to an array once it has been looked up at.
    """
    assert fmap.ndim >= 3, f"fmap must be [..., C, R, R], got {tuple(fmap.shape)}"
    lead, (c, r1, r2) = fmap.shape[:-3], fmap.shape[-3:]
    maps = fmap.reshape(-1, c, r1, r2)  # [B, C, R, R]
    if isinstance(uv, np.ndarray) and takes_kernels(maps, held=()):  # numba, at taps kept per point set
        from dlacli.avatar import lookup_kernels as lk

        at = _kept(uv, r1, r2, lk.corners)
        if maps.requires_grad and torch.is_grad_enabled():
            return _Lookup.apply(maps, at, _kept(uv, r1, r2, lk.transpose)).reshape(*lead, -1, c)
        return _gather(maps.detach(), at).reshape(*lead, -1, c)
    uv = torch.as_tensor(uv, dtype=fmap.dtype, device=fmap.device)
    grid = torch.stack([2.0 * uv[:, 0] - 1.0, 1.0 - 2.0 * uv[:, 1]], dim=-1)  # [N, 2] in [-1, 1]
    grid = grid[None, None].expand(maps.shape[0], 1, -1, 2)  # [B, 1, N, 2]
    out = nnf.grid_sample(maps, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[:, :, 0].transpose(1, 2).reshape(*lead, -1, c)  # [B, C, 1, N] -> [..., N, C]


_KEPT: dict[tuple, tuple] = {}  # (id(uv), what) -> (weakref to uv, H, W, what(uv, H, W))


def _kept(uv: np.ndarray, height: int, width: int, what):
    """what(uv, height, width) (`lookup_kernels.corners` or `transpose`) of points uv, kept while uv
    lives: samples are looked up every frame of an animation and every step of a refinement or a
    training run (`make_samples` hands out the same arrays again); the last few are kept."""
    import weakref

    key = (id(uv), what.__name__)
    hit = _KEPT.get(key)
    if hit is not None and hit[0]() is uv and hit[1:3] == (height, width):
        return hit[3]
    made = what(uv, height, width)
    if len(_KEPT) >= 8:
        _KEPT.pop(next(iter(_KEPT)))
    _KEPT[key] = (weakref.ref(uv), height, width, made)
    return made


def _gather(maps: torch.Tensor, at: tuple) -> torch.Tensor:
    """`lookup_kernels.gather` of maps [B, C, H, W] (CPU float32) at points whose `corners` are
    `at` -> [B, N, C]."""
    from dlacli.avatar.lookup_kernels import gather

    b, c, h, w = maps.shape
    out = torch.empty((b, at[0].shape[0], c), dtype=maps.dtype)
    gather(maps.reshape(b, c, h * w).transpose(1, 2).contiguous().numpy(), *at, h, w, out.numpy())  # channels last
    return out


class _Lookup(torch.autograd.Function):
    """The lookup of maps [B, C, H, W] at fixed points (their `corners` and the lookup's sparse
    transpose, avatar/lookup_kernels.py) -> [B, N, C], with float64 weights both ways: the values
    are `_gather`'s (grid_sample's bilinear, border, align_corners False, rounded once to float32)
    and the gradient to the maps is the transpose times the gradient, not depending on the thread
    count; no gradient to the points."""

    @staticmethod
    def forward(ctx, maps, at, transposed):
        ctx.transposed, ctx.shape = transposed, maps.shape
        return _gather(maps.detach(), at)

    @staticmethod
    def backward(ctx, grad):  # grad [B, N, C]
        from dlacli.avatar.lookup_kernels import texel_grads

        b, c, h, w = ctx.shape
        out = np.empty((b, h * w, c), np.float32)
        for k in range(b):
            texel_grads(*ctx.transposed, np.ascontiguousarray(grad[k].detach().numpy(), np.float32), out[k])
        return torch.from_numpy(out).transpose(1, 2).reshape(b, c, h, w), None, None


class _Sigmoid(torch.autograd.Function):
    """torch.sigmoid whose value does not depend on the thread count.

    torch's CPU sigmoid evaluates the elements of each thread's chunk with a vectorised formula
    and the chunk's last few (< 16) with a scalar one; the two differ in the last bit for ~4% of
    inputs, and the chunks follow the thread count (measured: N = 100,003, 1 vs 2 threads). Here
    1 / (1 + exp(-x)): exp, + and / gave the same bits for 1-8 threads; the gradient is torch's
    own sigmoid backward (also the same for any thread count). (docs/rendering.md "Determinism")
    """

    @staticmethod
    def forward(ctx, x):
        y = 1.0 / (1.0 + torch.exp(-x))  # x -> -inf: exp overflows to inf, y -> 0 as it should
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, g):
        (y,) = ctx.saved_tensors
        return torch.ops.aten.sigmoid_backward(g, y)


def sampled_params(fmap: torch.Tensor, samples: Samples) -> tuple[torch.Tensor, ...]:
    """F looked up at the samples and activated, in the tangent frame: dxyz [(P,) N, 3], unit
    dquat [(P,) N, 4], ds [(P,) N, 3], opacity [(P,) N], rgb [(P,) N, 3] (what `skinned_params`
    places; it depends on F and the samples alone, not on the pose)."""
    params = lookup(fmap, samples.uv)  # [(P,) N, 14]
    dquat = params[..., ROTATION]
    dquat = dquat / vector_norm(dquat).clamp_min(1e-8)
    ds = params[..., LOG_SCALE].exp()
    return params[..., OFFSET], dquat, ds, *_appearance(params)


def _appearance(params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Activated opacity [(P,) N] and rgb [(P,) N, 3] of looked-up channels [(P,) N, >= 4]."""
    return _Sigmoid.apply(params[..., 0]), params[..., RGB].clamp(0.0, 1.0)


def sampled_appearance(fmap: torch.Tensor, samples: Samples) -> tuple[torch.Tensor, torch.Tensor]:
    """(opacity, rgb) of `sampled_params`, from F's opacity and colour channels alone (the
    same numbers, bit for bit: the lookup weighs each channel on its own): what a map whose
    F_delta changes only appearance recomputes per camera."""
    return _appearance(lookup(fmap[..., : RGB.stop, :, :], samples.uv))  # opacity and rgb channels


def skinned_params(
    fmap: torch.Tensor,  # [14, R, R] one map F for all frames, or [P, 14, R, R] one per frame
    samples: Samples,
    frames: tuple[torch.Tensor, ...],  # T [P,N,3], R [P,N,3,3], S [P,N], Q [P,N,4] (`sample_frames`)
    sampled: tuple[torch.Tensor, ...] | None = None,  # `sampled_params(fmap, samples)`, when kept
):
    """Gaussian parameters for P posed frames (tangent frames precomputed at the samples):
    means [P, N, 3], quats [P, N, 4] (w, x, y, z), scales [P, N, 3], and opacities [N] /
    rgb [N, 3] for one map, [P, N] / [P, N, 3] for a map per frame (a batch: P avatars, or the
    F of a pose-conditioned decoder at each frame)."""
    from dlacli.body.skinning import skin_gaussians

    frames_T, frames_R, frames_S, frames_Q = frames
    assert fmap.ndim == 3 or fmap.shape[0] == frames_T.shape[0], (
        f"a batch of {fmap.shape[0]} maps needs as many frames, got {frames_T.shape[0]}"
    )
    dxyz, dquat, ds, opacity, rgb = sampled_params(fmap, samples) if sampled is None else sampled
    means, quats, scales = skin_gaussians(frames_T, frames_R, frames_S, dxyz, dquat, ds, frames_Q)
    return means, quats, scales, opacity, rgb


def skinned_params_on_body(
    fmap: torch.Tensor,  # [14, R, R] or [P, 14, R, R]
    samples: Samples,
    vertices: torch.Tensor,  # [P, V, 3] posed bodies
    frames=None,  # callable -> `sample_frames(vertices, samples)`, for the torch path
    sampled: tuple[torch.Tensor, ...] | None = None,  # `sampled_params(fmap, samples)`, when kept
):
    """`skinned_params` on posed vertices: the numba kernels when `kernel_path.takes_kernels` allows (the
    tangent frames are then never formed), else the torch path with `frames()` (or
    `sample_frames`). Same outputs, to float32 rounding."""
    from dlacli.body.skinning import skin_gaussians_on_body_fast

    if not takes_kernels(fmap, vertices):
        return skinned_params(fmap, samples, frames() if frames else sample_frames(vertices, samples), sampled)
    assert fmap.ndim == 3 or fmap.shape[0] == vertices.shape[0], (
        f"a batch of {fmap.shape[0]} maps needs as many bodies, got {vertices.shape[0]}"
    )
    with torch.no_grad():
        dxyz, dquat, ds, opacity, rgb = sampled_params(fmap, samples) if sampled is None else sampled
        means, quats, scales = skin_gaussians_on_body_fast(vertices, samples.face_id, samples.bary, dxyz, dquat, ds)
    return means, quats, scales, opacity, rgb


def posed_gaussians(fmap: torch.Tensor, samples: Samples, frames) -> Gaussians:
    """World Gaussians of P posed frames as one batch [P, N, ...] (see `skinned_params`): the
    differentiable path from maps [P, 14, R, R] (or one [14, R, R]) to `render_gaussians`."""
    means, quats, scales, opacity, rgb = skinned_params(fmap, samples, frames)
    p = means.shape[0]
    return Gaussians.from_rgb(means, quats, scales, opacity.expand(p, -1), rgb.expand(p, -1, -1))


def gaussians_at_frames(fmap: torch.Tensor, samples: Samples, frames) -> list[Gaussians]:
    """World Gaussians for each of P posed frames, one set each (see `posed_gaussians`)."""
    batch = posed_gaussians(fmap, samples, frames)
    return [batch.item(p) for p in range(batch.means.shape[0])]


def sample_frames(vertices: torch.Tensor, samples: Samples):
    """Tangent frames of posed vertices [P, V, 3] at the samples: positions T [P, N, 3],
    rotations R [P, N, 3, 3] and the same as quaternions Q [P, N, 4], scales S [P, N]."""
    from dlacli.body.uv import tangent_frames
    from dlacli.geometry import matrix_to_quat

    frames_T, frames_R, frames_S = tangent_frames(vertices, samples.face_id, samples.bary)
    return frames_T, frames_R, frames_S, matrix_to_quat(frames_R)
