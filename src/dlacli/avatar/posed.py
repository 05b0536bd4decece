"""The one path from an avatar to posed Gaussians (docs/architecture.md, "The layers": avatar/):

    avatar --Decoded--> F_c (once) --+ F_delta(pose p, camera c)--> F --lookup at the samples,
        skinning on body p (gaussian_map)--> Gaussians of body p seen from camera c --> splatting

`PosedAvatar` places a decoded avatar on P posed bodies, each seen from C cameras (their centres),
renders them (`PosedAvatar.render`) and handles the decoder's conditioning once for every consumer
(render, animate, export, rig, lift, the learned lift, training): the tangent frames of all bodies
at once, F_c once, the pose conditioning once per body, F_delta once per body when the decoder is
pose-conditioned and once per (body, camera) when it is view-conditioned. An unconditioned
decoder's F_c is skinned onto all P bodies as one batch; a conditioned decoder's maps are decoded
and skinned one at a time, each on its own body (the batch sizes the consumers used before:
batching changes the float summation order, and render, animate and export are pinned bit for
bit). Differentiable in the code: a `Decoded.of(decoder, z)` with z requiring grad gives
Gaussians with gradients to z.

`sample_settings` is the sample-count/seed policy: which surface samples an avatar is drawn at.
`render_set` splats one set of placed Gaussians, with appearance per camera where given (what the
pipeline's render calls, and what renders Gaussians placed elsewhere: an animation's frames).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from dlacli.avatar import gaussian_map as gm
from dlacli.avatar.codec import Decoded
from dlacli.errors import DlaInputError
from dlacli.kernel_path import takes_kernels
from dlacli.limits import DEFAULT_GAUSSIANS, MAX_GAUSSIANS, MAX_SEED, MIN_GAUSSIANS
from dlacli.types import Avatar, Cameras, Gaussians, rgb_to_sh0

CAMERAS_PER_CALL = 8  # splat this many cameras at once: projections are [C, N, ...], memory grows with C


def sample_settings(avatar: Avatar, n_gaussians: int | None = None, seed: int | None = None) -> tuple[int, int]:
    """(Gaussian count, sample seed): the given ones, else what the avatar records
    (`extra.samples`, written by lift: the points its Gaussians were refined at), else the
    defaults (DEFAULT_GAUSSIANS, 0)."""
    recorded = avatar.extra.get("samples", {}) if isinstance(avatar.extra.get("samples"), dict) else {}
    count = n_gaussians if n_gaussians is not None else recorded.get("count", DEFAULT_GAUSSIANS)
    seed = seed if seed is not None else recorded.get("seed", 0)
    if not isinstance(count, int) or isinstance(count, bool) or not MIN_GAUSSIANS <= count <= MAX_GAUSSIANS:
        raise DlaInputError(
            "avatar", f"extra.samples.count must be an integer in [{MIN_GAUSSIANS}, {MAX_GAUSSIANS}], got {count!r}"
        )
    if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed <= MAX_SEED:
        raise DlaInputError("avatar", f"extra.samples.seed must be an integer in [0, {MAX_SEED}], got {seed!r}")
    return count, seed


def avatar_samples(avatar: Avatar, n_gaussians: int | None = None, seed: int | None = None) -> gm.Samples:
    """The surface samples an avatar's Gaussians are drawn at (`sample_settings`)."""
    return gm.make_samples(*sample_settings(avatar, n_gaussians, seed))


@dataclass
class Placed:
    """Gaussians of a map F placed on P posed bodies (activated, as `gaussian_map.skinned_params`
    gives them) and the F_delta that made F."""

    means: torch.Tensor  # [P, N, 3]
    quats: torch.Tensor  # [P, N, 4] (w, x, y, z)
    scales: torch.Tensor  # [P, N, 3]
    opacities: torch.Tensor  # [N]: one map F for every body (F_c), or [P, N]: one per body
    rgb: torch.Tensor  # [N, 3] or [P, N, 3], in [0, 1]
    delta: torch.Tensor | None = None  # [P, 14, R, R] F_delta of each body's F; None: F = F_c

    def item(self, p: int = 0) -> Gaussians:
        """The Gaussians [N] on body p."""
        opacities = self.opacities if self.opacities.ndim == 1 else self.opacities[p]
        rgb = self.rgb if self.rgb.ndim == 2 else self.rgb[p]
        return Gaussians.from_rgb(self.means[p], self.quats[p], self.scales[p], opacities, rgb)


def _stack(parts: list[Placed]) -> Placed:
    if len(parts) == 1:
        return parts[0]
    deltas = [x.delta for x in parts]
    delta = None if any(d is None for d in deltas) else torch.cat(deltas)
    fields = ("means", "quats", "scales", "opacities", "rgb")
    return Placed(*(torch.cat([getattr(x, k) for x in parts]) for k in fields), delta)


class PosedAvatar:
    """A decoded avatar on P posed bodies (vertices [P, V, 3]), body p seen from its C cameras:
    `cameras` one Cameras every body is seen from, or a sequence of P (one per body, C each), which
    `render` draws; or, to place the Gaussians without rendering (a USD file's view), only the
    cameras' centres, eyes [P, C, 3]. Neither: no camera (e.g. rigging). Module docstring: what
    is computed once and what per body and camera. `canonical_only`: place F_c alone, as if the
    decoder were unconditioned (what a rig can carry)."""

    def __init__(
        self,
        decoded: Decoded,
        samples: gm.Samples,
        vertices: torch.Tensor,
        cameras: Cameras | Sequence[Cameras] | None = None,
        *,
        eyes: torch.Tensor | None = None,
        canonical_only: bool = False,
    ):
        from dlacli.geometry import camera_centers

        assert vertices.ndim == 3 and vertices.shape[-1] == 3, f"vertices [P, V, 3], got {tuple(vertices.shape)}"
        p = vertices.shape[0]
        assert cameras is None or eyes is None, "cameras or eyes, not both"
        self.views: list[Cameras] | None = None
        if cameras is not None:
            self.views = [cameras] * p if isinstance(cameras, Cameras) else list(cameras)
            assert len(self.views) == p and len({len(c) for c in self.views}) == 1, "one Cameras per body, C each"
            # the centres from the float32 matrices on the CPU, then moved (what every caller computed)
            centres = [camera_centers(c.viewmats.float()) for c in self.views]
            eyes = (centres[0][None].expand(p, -1, -1) if isinstance(cameras, Cameras) else torch.stack(centres)).to(
                vertices.device
            )
        assert eyes is None or (eyes.ndim == 3 and eyes.shape[0] == p and eyes.shape[-1] == 3), (
            f"eyes must be [{p}, C, 3], got {None if eyes is None else tuple(eyes.shape)}"
        )
        self.decoded, self.samples, self.vertices, self.eyes = decoded, samples, vertices, eyes
        self._frames: tuple | None = None  # tangent frames of all P bodies, once the torch path asks
        self.conditioned = decoded.conditioned and not canonical_only
        self._poses: dict[int, object] = {}  # pose conditioning per body
        self._all: Placed | None = None  # F_c on every body (unconditioned)
        self._geometry: dict[int, tuple] = {}  # F_c's skinned geometry per body (`_appearance_only`)

    def __len__(self) -> int:
        return self.vertices.shape[0]

    @property
    def frames(self) -> tuple[torch.Tensor, ...]:
        """The tangent frames of all P bodies at the samples (`gaussian_map.sample_frames`),
        computed once when first asked (the numba path of `skinned_params_on_body` needs none)."""
        if self._frames is None:
            self._frames = gm.sample_frames(self.vertices, self.samples)
        return self._frames

    def _skin(self, fmap: torch.Tensor, p: int | None = None) -> tuple[torch.Tensor, ...]:
        """`gaussian_map.skinned_params_on_body` of fmap on body p (None: all bodies); F_c looked
        up at the samples once per decoded avatar when no gradient is asked for."""
        one = slice(None) if p is None else slice(p, p + 1)
        sampled = self.decoded.sampled_canonical(self.samples) if fmap is self.decoded.f_c else None
        return gm.skinned_params_on_body(
            fmap, self.samples, self.vertices[one], lambda: tuple(f[one] for f in self.frames), sampled
        )

    @property
    def cameras(self) -> int:
        """C, the cameras per body (0 without eyes)."""
        return 0 if self.eyes is None else self.eyes.shape[1]

    @property
    def per_camera(self) -> bool:
        """Whether each camera sees Gaussians of its own (a view-conditioned decoder's F_delta)."""
        return self.conditioned and self.decoded.decoder.view_conditioned and self.eyes is not None

    def placed(self, p: int, c: int = 0) -> Placed:
        """Body p seen from its camera c: Placed with P = 1."""
        if not self.conditioned:
            return self.all() if len(self) == 1 else self._slice(self.all(), p)
        dec = self.decoded
        if p not in self._poses:
            self._poses[p] = dec.pose(self.vertices[p])
        pose = self._poses[p]
        rays = dec.rays(self.vertices[p], self.eyes[p, c], pose) if self.eyes is not None else None
        delta = dec.delta(pose, rays)
        placed = self._appearance_only(delta, p)
        if placed is None:
            placed = self._skin(dec.f_c if delta is None else dec.f_c + delta, p)
        means, quats, scales, opacities, rgb = placed
        return Placed(means, quats, scales, opacities[None], rgb[None], None if delta is None else delta[None])

    def _appearance_only(self, delta: torch.Tensor | None, p: int) -> tuple[torch.Tensor, ...] | None:
        """`_skin(F_c + delta, p)` when F_delta changes only opacity and colour (the decoder's
        `delta_geometry` is off) and no gradient is asked for: the geometry is F_c's, skinned once
        per body, and only the appearance channels of F are added and looked up per camera (the
        same numbers, bit for bit). None where this does not apply."""
        dec = self.decoded
        maps = (dec.f_c,) if delta is None else (dec.f_c, delta)
        if dec.decoder.delta_geometry or not takes_kernels(*maps, self.vertices):
            return None
        if dec.sampled_canonical(self.samples) is None:
            return None
        if p not in self._geometry:
            self._geometry[p] = self._skin(dec.f_c, p)[:3]
        shown = slice(0, gm.RGB.stop)  # opacity and colour
        fmap = dec.f_c[shown] if delta is None else dec.f_c[shown] + delta[shown]
        return (*self._geometry[p], *gm.sampled_appearance(fmap, self.samples))

    def all(self, c: int = 0) -> Placed:
        """Every body, seen from its camera c: Placed with P = len(self)."""
        if not self.conditioned:
            if self._all is None:
                self._all = Placed(*self._skin(self.decoded.f_c))
            return self._all
        return _stack([self.placed(p, c) for p in range(len(self))])

    def gaussians(self, p: int = 0, c: int = 0) -> Gaussians:
        """The Gaussians [N] of body p seen from its camera c."""
        return self.placed(p, c).item(0)

    @staticmethod
    def _slice(x: Placed, p: int) -> Placed:
        one = slice(p, p + 1)
        shared = x.opacities.ndim == 1
        opacities, rgb = (x.opacities, x.rgb) if shared else (x.opacities[one], x.rgb[one])
        return Placed(x.means[one], x.quats[one], x.scales[one], opacities, rgb)

    def renders(
        self, body: int = 0, per_call: int = CAMERAS_PER_CALL, exact: bool = True, deltas: list | None = None
    ) -> Iterator[tuple[np.ndarray, object]]:
        """Splat body `body` from its cameras, in order -> (camera indices [k], RenderOutput
        [k, H, W]) per call of the renderer: `per_call` cameras at once, their Gaussians one set or,
        where each camera sees its own colours (`per_camera`), one geometry with appearance per
        camera (`render_gaussians(opacities=, sh=)`); each camera alone where F_delta moves the
        geometry too.
        Differentiable like `render_gaussians`; `exact=False` as there (playback). `deltas`: a
        list that gets each camera's F_delta [1, 14, R, R] (None without one)."""
        assert self.views is not None, "no cameras to render from"
        cams = self.views[body]
        if not self.per_camera:
            placed = self.placed(body)
            if deltas is not None:
                deltas.extend([placed.delta] * len(cams))
            yield from _render_calls(placed.item(0), cams, None, None, exact, per_call)
            return
        step = 1 if self.decoded.decoder.delta_geometry else max(1, per_call)
        for k in range(0, len(cams), step):
            group = np.arange(k, min(k + step, len(cams)))
            placed = [self.placed(body, int(c)) for c in group]
            if deltas is not None:
                deltas.extend(x.delta for x in placed)
            if len(group) == 1 or _asks_grad(placed[0].means, placed[0].rgb):
                # with a gradient, each camera its own set, as before: the same gradients, bit for bit
                for c, x in zip(group, placed):
                    for _, out in _render_calls(x.item(0), cams.select([int(c)]), None, None, exact, None):
                        yield group[group == c], out
                continue
            geometry = placed[0].item(0)
            opacities = torch.cat([x.opacities for x in placed])  # [k, N]
            sh = rgb_to_sh0(torch.cat([x.rgb for x in placed]))[..., None, :]  # [k, N, 1, 3], as from_rgb
            for sub, out in _render_calls(geometry, cams.select(group), opacities, sh, exact, None):
                yield group[sub], out

    def render(self, body: int = 0, per_call: int = CAMERAS_PER_CALL, exact: bool = True, deltas: list | None = None):
        """`renders` of body `body`, joined: RenderOutput [C, H, W] for its C cameras."""
        return join_renders(out for _, out in self.renders(body, per_call, exact, deltas))


def render_set(
    gaussians: Gaussians,
    cameras: Cameras,
    opacities: torch.Tensor | None = None,
    sh: torch.Tensor | None = None,
    *,
    exact: bool = True,
    per_call: int | None = None,
):
    """Splat one set of placed Gaussians [N] from C cameras, with each camera's own opacities
    [C, N] and SH sh [C, N, K, 3] where given -> RenderOutput [C, H, W]: `per_call` cameras a call
    of the renderer (None: all at once). Differentiable like `render_gaussians`; `exact=False` as
    there (playback)."""
    return join_renders(out for _, out in _render_calls(gaussians, cameras, opacities, sh, exact, per_call))


def _render_calls(gaussians, cameras, opacities, sh, exact, per_call) -> Iterator[tuple[np.ndarray, object]]:
    """`render_set` call by call -> (camera indices [k], RenderOutput [k, H, W]). Where a gradient
    is asked for and the appearance is per camera, each camera alone: autograd then adds up each
    camera's gradient of the shared geometry as the refinement and the trainings always have, so
    their results stay the same bits."""
    from dlacli.render.splat import render_gaussians

    tracked = _asks_grad(gaussians.means, gaussians.opacities, gaussians.sh, opacities, sh)
    step = len(cameras) if per_call is None else max(1, per_call)
    step = 1 if tracked and (opacities is not None or sh is not None) else step
    for k in range(0, len(cameras), step):
        part = slice(k, min(k + step, len(cameras)))
        picked = [None if t is None else t[part] for t in (opacities, sh)]
        out = render_gaussians(gaussians, cameras.select(part), exact=exact, opacities=picked[0], sh=picked[1])
        yield np.arange(part.start, part.stop), out


def _asks_grad(*tensors) -> bool:
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def join_renders(outs) -> object:
    """RenderOutputs [k_i, H, W] of consecutive cameras -> one RenderOutput [sum k_i, H, W]."""
    from dlacli.render.splat import RenderOutput

    outs = list(outs)
    if len(outs) == 1:
        return outs[0]
    return RenderOutput(*(torch.cat(parts) for parts in zip(*outs)))
