"""Geometry shared by every layer: rotations, pinhole projection, look-at cameras, Plucker rays.

Bottom layer (docs/architecture.md, "The layers"): imports only numpy, torch and dlacli.types. Conventions are those of
docs/conventions.md, not restated here beyond what a signature needs:
- rotations: matrices rotate column vectors (x' = R x); axis-angle = rotation vector (direction =
  axis, norm = angle, radians); quaternions (w, x, y, z), Hamilton product; `matrix_to_quat` and
  `axis_angle_to_quat` return the representative with w >= 0;
- cameras in memory: world-to-camera `viewmats` [..., 4, 4] in OpenCV axes (+X right, +Y down,
  looking down +Z), intrinsics `Ks` [..., 3, 3] in pixels (skew ignored: always 0 here); pixel
  (col j, row i) has its centre at (j + 0.5, i + 0.5); on disk camera-to-world in OpenGL axes;
- Plucker ray of origin o and unit direction d: the 6 channels (d, o x d).

Torch functions work on any leading batch shape, keep the inputs' dtype and device (mixed float
dtypes are promoted) and are differentiable; the rotations have finite gradients everywhere,
including at the zero rotation (series expansions) and near a half turn (the log map goes through
quaternions). Functions marked "numpy in, numpy out" also take numpy arrays and then return numpy
arrays of the promoted input dtype (the same formulas, without autograd); mixing numpy arrays and
tensors in one call is a TypeError. The section "rotations in numpy" (quaternion order for file
formats, slerp, sign-continuous tracks, the rotation between two directions, Kabsch fits) is numpy
only, for the readers, writers and retargeting that work on numpy arrays.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from dlacli.types import Cameras

_SMALL = 1e-6  # below this angle (squared: _SMALL**2) the closed forms switch to Taylor series
DEPTH_EPS = 1e-6  # default near-plane guard of the perspective divide (metres), see camera_to_pixels


def _numpy_in_numpy_out(fn):
    """numpy arrays in -> numpy arrays out: ndarray arguments become tensors of one promoted float
    dtype (zero-copy where possible), the torch code runs without autograd, tensor results come
    back as ndarrays. Tensors in -> the function itself (mixing the two is an error)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        arrays = [a for a in args if isinstance(a, np.ndarray)]
        if not arrays:
            return fn(*args, **kwargs)
        if any(isinstance(a, torch.Tensor) for a in args):
            raise TypeError(f"{fn.__name__}: pass all numpy arrays or all torch tensors, not both")
        dtype = np.result_type(*arrays)
        if not np.issubdtype(dtype, np.floating):
            dtype = np.dtype(np.float64)

        def to_torch(a):
            a = np.ascontiguousarray(a, dtype=dtype)
            return torch.from_numpy(a if a.flags.writeable else a.copy())

        with torch.no_grad():
            out = fn(*(to_torch(a) if isinstance(a, np.ndarray) else a for a in args), **kwargs)
        if isinstance(out, tuple):
            return tuple(o.numpy() if isinstance(o, torch.Tensor) else o for o in out)
        return out.numpy()

    return wrapper


def _promote(*ts: torch.Tensor) -> list[torch.Tensor]:
    dtype = functools.reduce(torch.promote_types, [t.dtype for t in ts])
    return [t.to(dtype) for t in ts]


# ----------------------------------------------------------------------------------- rotations


@_numpy_in_numpy_out
def skew(v: torch.Tensor) -> torch.Tensor:
    """v [..., 3] -> [..., 3, 3] cross-product matrix: skew(v) @ x == cross(v, x)."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


@_numpy_in_numpy_out
def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula: aa [..., 3] axis-angle -> [..., 3, 3] rotation matrix."""
    theta2 = (aa * aa).sum(-1)  # [...]
    small = theta2 < _SMALL**2
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = safe2.sqrt()
    # a = sin(t) / t, b = (1 - cos(t)) / t^2, with series near t = 0
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    k = skew(aa)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def quat_rotation_rows(q):
    """q [..., 4] (w, x, y, z), used as given (not normalised; numpy or torch) -> the rotation
    matrix as rows of entries R[i][j], 9 arrays [...]: elementwise, with no [..., 3, 3] temporary
    (`dlacli.io.usd.instance_extent` sums them directly)."""
    w, x, y, z = (q[..., k] for k in range(4))
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return [
        [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
        [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
        [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)],
    ]


@_numpy_in_numpy_out
def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """q [..., 4] (w, x, y, z) -> [..., 3, 3]; q need not be normalised (it is, first)."""
    q = q / q.norm(dim=-1, keepdim=True)
    m = torch.stack([entry for row in quat_rotation_rows(q) for entry in row], dim=-1)
    return m.reshape(*q.shape[:-1], 3, 3)


@_numpy_in_numpy_out
def matrix_to_quat(m: torch.Tensor) -> torch.Tensor:
    """m [..., 3, 3] rotation -> [..., 4] unit (w, x, y, z) with w >= 0.

    Shepperd's method: of the four ways to read the quaternion off the matrix, use the one whose
    pivot component (|w|, |x|, |y| or |z|) is largest, so no division by a small number happens.
    """
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 * squared components: [..., 4] for (w, x, y, z)
    sq = torch.stack(
        [
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ],
        dim=-1,
    )
    pivot = sq.clamp_min(0.1).sqrt()  # [..., 4] 2|q_i|, only used where it is the largest (>= 1)
    # candidate quaternions (times 2 * pivot), one per pivot: [..., 4 candidates, 4 components]
    cand = torch.stack(
        [
            torch.stack([pivot[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], dim=-1),
            torch.stack([m21 - m12, pivot[..., 1] ** 2, m10 + m01, m02 + m20], dim=-1),
            torch.stack([m02 - m20, m10 + m01, pivot[..., 2] ** 2, m12 + m21], dim=-1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, pivot[..., 3] ** 2], dim=-1),
        ],
        dim=-2,
    )
    cand = cand / (2.0 * pivot[..., None])
    best = sq.argmax(dim=-1)  # [...]
    q = torch.gather(cand, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


@_numpy_in_numpy_out
def axis_angle_to_quat(aa: torch.Tensor) -> torch.Tensor:
    """aa [..., 3] axis-angle -> [..., 4] unit (w, x, y, z) with w >= 0."""
    theta2 = (aa * aa).sum(-1, keepdim=True)
    small = theta2 < _SMALL**2
    theta = torch.where(small, torch.ones_like(theta2), theta2).sqrt()
    half_sinc = torch.where(small, 0.5 - theta2 / 48.0, torch.sin(0.5 * theta) / theta)
    w = torch.where(small, 1.0 - theta2 / 8.0, torch.cos(0.5 * theta))
    q = torch.cat([w, aa * half_sinc], dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)


@_numpy_in_numpy_out
def quat_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    """q [..., 4] (w, x, y, z) -> [..., 3] axis-angle with angle in [0, pi].

    Uses angle = 2 atan2(|v|, w) after flipping q to w >= 0, which is accurate near 0 and near pi.
    """
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[..., :1] < 0, -q, q)
    w, v = q[..., :1], q[..., 1:]
    n2 = (v * v).sum(-1, keepdim=True)
    small = n2 < _SMALL**2
    n = torch.where(small, torch.ones_like(n2), n2).sqrt()
    angle = 2.0 * torch.atan2(n, w)
    # angle / |v|; near |v| = 0 (then w ~ 1): 2 / w * (1 - |v|^2 / (3 w^2))
    scale = torch.where(small, 2.0 / w * (1.0 - n2 / (3.0 * w * w)), angle / n)
    return v * scale


@_numpy_in_numpy_out
def matrix_to_axis_angle(m: torch.Tensor) -> torch.Tensor:
    """Log map: m [..., 3, 3] rotation -> [..., 3] axis-angle, angle in [0, pi] (robust near pi)."""
    return quat_to_axis_angle(matrix_to_quat(m))


@_numpy_in_numpy_out
def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of a, b [..., 4] (w, x, y, z) (rotation b first, then a) -> [..., 4]."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


@_numpy_in_numpy_out
def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """q [..., 4] -> [..., 4] conjugate (the inverse for unit quaternions)."""
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype, device=q.device)


def quat_normalize(q, eps: float = 1e-12):
    """q [..., 4] -> [..., 4] unit quaternion (norms below eps are treated as eps, so zero rows
    stay zero). numpy in, numpy out, computed in numpy (the norm summed by einsum, as the USD
    reader and writer have always done) and in the input's dtype."""
    if isinstance(q, np.ndarray):
        return q / np.maximum(np.sqrt(np.einsum("...i,...i->...", q, q))[..., None], eps)
    return q / q.norm(dim=-1, keepdim=True).clamp_min(eps)


# ----------------------------------------------------------------------- rotations in numpy
# numpy in, numpy out, no torch: the conventions above.


def quat_wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """[..., 4] (w, x, y, z) -> [..., 4] (x, y, z, w), the order of pxr's Vt.Quat*Array and scipy."""
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def quat_xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """[..., 4] (x, y, z, w) -> [..., 4] (w, x, y, z)."""
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def quat_slerp(a: np.ndarray, b: np.ndarray, t, shortest: bool = False) -> np.ndarray:
    """Spherical interpolation from a to b [..., 4] (unit) at t ([...] with a trailing 1, or a
    scalar, in [0, 1]) -> [..., 4], GfSlerp's formula: the angle is 2 atan2(|a - b|, |a + b|)
    (accurate near 0), linear weights below 1e-6 rad. It follows the arc from a to b as given,
    the long way when <a, b> < 0, unless `shortest` negates such b first (q and -q are one rotation)."""
    if shortest:
        b = np.where(np.sum(a * b, axis=-1, keepdims=True) < 0, -b, b)
    phi = 2 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))[..., None]
    small = phi < 1e-6
    sin_phi = np.where(small, 1.0, np.sin(phi))
    wa = np.where(small, 1 - t, np.sin((1 - t) * phi) / sin_phi)
    wb = np.where(small, t, np.sin(t * phi) / sin_phi)
    return wa * a + wb * b


def quat_continuous_signs(q: np.ndarray) -> np.ndarray:
    """[T, n, 4] a quaternion track -> the same rotations with <q[t], q[t-1]> >= 0 (sign flips
    taken out, compared in float32), so interpolating neighbouring samples takes the short way."""
    q = q.copy()
    for t in range(1, q.shape[0]):
        dot = np.einsum("nd,nd->n", q[t].astype(np.float32), q[t - 1].astype(np.float32))
        q[t] *= np.where(dot < 0, -1, 1).astype(q.dtype)[:, None]
    return q


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[3, 3] the shortest rotation turning direction a [3] onto direction b [3] (about a x b;
    opposite directions: a half turn about an axis perpendicular to a)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-9:  # opposite: turn 180 degrees about any axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def rigid_motion(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """positions [T, n, 3] -> (R [T, 3, 3], c [T, 3]) float64, the rotation and translation that
    best carry frame 0's shape (about its centroid) onto frame t's (Kabsch, no reflection):
    p_t ~ R_t (p_0 - mean_0) + c_t. R_0 = I, c_t = mean_t."""
    p = positions.astype(np.float64)
    mean = p.mean(axis=1)  # [T, 3]
    a = p[0] - mean[0]  # [n, 3]
    h = np.einsum("ni,tnj->tij", a, p - mean[:, None])  # [T, 3, 3] cross-covariance
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("tji,tkj->tik", vt, u)))  # det(V U^T)
    fix = np.ones((p.shape[0], 3))
    fix[:, 2] = np.where(d == 0, 1, d)
    r = np.einsum("tji,tj,tkj->tik", vt, fix, u)  # V diag(1, 1, d) U^T
    r[0] = np.eye(3)
    return r, mean


def similarity_fit(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None):
    """The similarity that best carries points src [N, 3] onto dst [N, 3] (weighted Umeyama, no
    reflection): (s, R [3, 3], t [3]) float64 minimising sum_i w_i |s R src_i + t - dst_i|^2;
    weights [N] >= 0 (None: equal). Exact when dst is a similarity of src."""
    p = np.asarray(src, np.float64)
    q = np.asarray(dst, np.float64)
    w = np.ones(len(p)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    mp, mq = w @ p, w @ q
    a, b = p - mp, q - mq
    cov = (b * w[:, None]).T @ a  # [3, 3] sum_i w_i b_i a_i^T
    u, sv, vt = np.linalg.svd(cov)
    d = np.ones(3)
    d[2] = -1.0 if np.linalg.det(u) * np.linalg.det(vt) < 0 else 1.0
    r = (u * d) @ vt
    s = float((sv * d).sum() / (w @ (a * a).sum(axis=1)))
    return s, r, mq - s * r @ mp


def similarity_cameras(cameras: Cameras, s: float, r: np.ndarray, t: np.ndarray) -> Cameras:
    """The same cameras in a world moved by the similarity x' = s R x + t: every camera sees the
    moved world as it saw the old one (the same pixels; depths scale by s). Intrinsics unchanged."""
    vm = cameras.viewmats.detach().cpu().double().numpy()  # [C, 4, 4]
    out = vm.copy()
    out[:, :3, :3] = vm[:, :3, :3] @ r.T
    out[:, :3, 3] = s * vm[:, :3, 3] - out[:, :3, :3] @ np.asarray(t, np.float64)
    return Cameras(torch.from_numpy(out).to(cameras.viewmats.dtype), cameras.Ks.clone(), cameras.width, cameras.height)


# ---------------------------------------------------------------------------------- projection


def _array_args(*xs):
    """All numpy (-> as float arrays) or all torch (-> promoted to one dtype); numpy code runs as
    numpy (faster than a round trip through torch for these elementwise formulas)."""
    if any(isinstance(x, torch.Tensor) for x in xs):
        if not all(isinstance(x, torch.Tensor) for x in xs):
            raise TypeError("pass all numpy arrays or all torch tensors, not both")
        return _promote(*xs)
    return [np.asarray(x) if np.issubdtype(np.asarray(x).dtype, np.floating) else np.asarray(x, np.float64) for x in xs]


def world_to_camera(points, viewmats):
    """points [..., N, 3] world, viewmats [..., 4, 4] world-to-camera -> [..., N, 3] camera frame.

    Leading dimensions broadcast: points [N, 3] with viewmats [C, 4, 4] give [C, N, 3].
    numpy in, numpy out.
    """
    points, viewmats = _array_args(points, viewmats)
    return points @ viewmats[..., :3, :3].swapaxes(-1, -2) + viewmats[..., None, :3, 3]


def camera_to_pixels(points_cam, Ks, near: float = DEPTH_EPS):
    """points_cam [..., N, 3] camera frame (OpenCV axes), Ks [..., 3, 3] -> pixels [..., N, 2] (x, y).

    u = fx x / z + cx, v = fy y / z + cy in continuous pixel coordinates. Near-plane guard: the
    divisor is max(z, near) (a clamp: no gradient through z there), so points at or behind the
    camera get finite pixels that mean nothing; tell them apart by their depth (z > near).
    numpy in, numpy out.
    """
    points_cam, Ks = _array_args(points_cam, Ks)
    z = points_cam[..., 2]
    z = z.clamp(min=near) if isinstance(z, torch.Tensor) else np.maximum(z, near)  # [..., N]
    u = Ks[..., None, 0, 0] * points_cam[..., 0] / z + Ks[..., None, 0, 2]
    v = Ks[..., None, 1, 1] * points_cam[..., 1] / z + Ks[..., None, 1, 2]
    return torch.stack([u, v], dim=-1) if isinstance(u, torch.Tensor) else np.stack([u, v], axis=-1)


def project_points(points, viewmats, Ks, near: float = DEPTH_EPS):
    """Pinhole projection: points [..., N, 3] world, viewmats [..., 4, 4], Ks [..., 3, 3] ->
    (pixels [..., N, 2], depth [..., N] = camera z, unguarded). See `camera_to_pixels` for the
    near-plane guard; leading dimensions broadcast as in `world_to_camera`. numpy in, numpy out."""
    pc = world_to_camera(points, viewmats)
    return camera_to_pixels(pc, Ks, near), pc[..., 2]


def project_to_cameras(points, cameras: Cameras, near: float = DEPTH_EPS):
    """points [N, 3] (or [C, N, 3]: one set per camera) world -> (pixels [C, N, 2], depth [C, N])
    for every camera of `cameras`. numpy points: computed and returned in float64; torch points:
    in their dtype and on their device (cameras are cast to them)."""
    if isinstance(points, torch.Tensor):
        vm, ks = cameras.viewmats.to(points), cameras.Ks.to(points)
    else:
        points = np.asarray(points, np.float64)
        vm, ks = cameras.viewmats.detach().cpu().double().numpy(), cameras.Ks.detach().cpu().double().numpy()
    return project_points(points, vm, ks, near)


@_numpy_in_numpy_out
def camera_centers(viewmats: torch.Tensor) -> torch.Tensor:
    """viewmats [..., 4, 4] world-to-camera -> camera centres [..., 3] in the world (-R^T t for a
    rigid one; computed from the inverse, so matrices rounded to float32 stay consistent with
    `project_points`). numpy in, numpy out."""
    return torch.linalg.inv(viewmats)[..., :3, 3]


# ----------------------------------------------------------------------- look-at / orbit cameras
# Azimuth 0 is on the -Y side (in front of a body at rest), 90 on +X; elevation is up from the
# horizontal plane; all angles in degrees (docs/conventions.md). numpy, float64.


def look_at_c2w(eyes: np.ndarray, targets: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world [C, 4, 4] in OpenGL axes for eyes [C, 3] looking at targets [C, 3] (or [3])."""
    eyes = np.atleast_2d(np.asarray(eyes, np.float64))
    targets = np.broadcast_to(np.asarray(targets, np.float64), eyes.shape)
    back = eyes - targets
    back /= np.linalg.norm(back, axis=1, keepdims=True)
    right = np.cross(np.asarray(up, np.float64), back)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    cam_up = np.cross(back, right)
    c2w = np.zeros((eyes.shape[0], 4, 4))
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, cam_up, back, eyes
    c2w[:, 3, 3] = 1.0
    return c2w


def orbit_eyes(target, distance: float, azimuths, elevations) -> np.ndarray:
    """Eye positions [C, 3] at `distance` from target [3] (azimuths [C], elevations [C] or scalar,
    degrees)."""
    az = np.radians(np.atleast_1d(np.asarray(azimuths, np.float64)))
    el = np.radians(np.broadcast_to(np.asarray(elevations, np.float64), az.shape))
    offset = np.stack([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)], axis=1)
    return np.asarray(target, np.float64) + distance * offset


def pinhole_cameras(c2w: np.ndarray, fov_deg: float, width: int, height: int | None = None) -> Cameras:
    """Cameras from camera-to-world c2w [C, 4, 4] (OpenGL axes) with a vertical field of view
    (degrees), principal point at the image centre; square images unless height is given."""
    height = width if height is None else height
    f = 0.5 * height / np.tan(np.radians(fov_deg) / 2.0)
    return Cameras.from_c2w_opengl(c2w, f, f, width / 2.0, height / 2.0, width, height)


def look_at_orbit_cameras(
    target, distance: float, azimuths, elevations, fov_deg: float, width: int, height: int | None = None
) -> Cameras:
    """Cameras on a sphere of radius `distance` around target [3] at azimuths [C] / elevations
    ([C] or scalar, degrees), each looking at the target, +Z up."""
    eyes = orbit_eyes(target, distance, azimuths, elevations)
    return pinhole_cameras(look_at_c2w(eyes, np.asarray(target, np.float64)), fov_deg, width, height)


def framing_distance(extent: float, fov_deg: float, margin: float = 1.15) -> float:
    """Distance at which a subject `extent` metres tall fills the field of view (with a margin)."""
    return 0.5 * extent * margin / np.tan(np.radians(fov_deg) / 2.0)


def smooth_path(path: np.ndarray, fps: float, seconds: float = 0.5) -> np.ndarray:
    """Moving average of a path [T, D] over `seconds` (edges padded), for steady follow cameras."""
    window = max(1, int(round(seconds * fps)))
    kernel = np.ones(window) / window
    pad = ((window // 2, window - 1 - window // 2), (0, 0))
    padded = np.pad(np.asarray(path, np.float64), pad, mode="edge")
    return np.stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(padded.shape[1])], axis=1)


# ------------------------------------------------------------------------------- Plucker rays


def vector_norm(x: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """The Euclidean norm of x along dim, keepdim. Without a gradient to keep, sqrt of the sum of
    squares: torch 2.13's CPU `norm` over a short axis of 3 runs ~40x slower (measured: 12 ms vs
    0.3 ms for [65536, 3]); with one, `norm` (its subgradient at a zero vector is 0, sqrt's is not)."""
    if torch.is_grad_enabled() and x.requires_grad:
        return x.norm(dim=dim, keepdim=True)
    return (x * x).sum(dim=dim, keepdim=True).sqrt()


@_numpy_in_numpy_out
def plucker(origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """origins [..., 3], directions [..., 3] (any length; broadcast) -> [..., 6] (d, o x d) with d
    the unit direction. Every point p on the ray satisfies p x d = o x d (the moment). A zero
    direction gives zeros. numpy in, numpy out."""
    origins, directions = _promote(origins, directions)
    d = directions / vector_norm(directions).clamp_min(1e-12)
    o, d = torch.broadcast_tensors(origins, d)
    return torch.cat([d, torch.linalg.cross(o, d, dim=-1)], dim=-1)


def pixel_rays(cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays through every pixel centre (j + 0.5, i + 0.5) of every camera:
    -> (origins [C, H, W, 3] = camera centres, unit directions [C, H, W, 3]), in the cameras'
    dtype and device."""
    vm, ks = cameras.viewmats, cameras.Ks
    kw = {"dtype": vm.dtype, "device": vm.device}
    cols = torch.arange(cameras.width, **kw) + 0.5  # [W]
    rows = torch.arange(cameras.height, **kw) + 0.5  # [H]
    x = (cols[None, None, :] - ks[:, 0, 2, None, None]) / ks[:, 0, 0, None, None]  # [C, 1, W]
    y = (rows[None, :, None] - ks[:, 1, 2, None, None]) / ks[:, 1, 1, None, None]  # [C, H, 1]
    x, y = torch.broadcast_tensors(x, y)  # [C, H, W]
    d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)  # [C, H, W, 3] OpenCV camera frame
    c2w = torch.linalg.inv(vm)  # [C, 4, 4] (the exact inverse of what project_points applies)
    d = torch.einsum("cij,chwj->chwi", c2w[:, :3, :3], d_cam)
    d = d / d.norm(dim=-1, keepdim=True)
    o = c2w[:, None, None, :3, 3].expand_as(d)
    return o, d


def plucker_rays(cameras: Cameras) -> torch.Tensor:
    """Image-space Plucker ray map of every camera: -> [C, H, W, 6] (d, o x d), world frame,
    through the pixel centres (`pixel_rays`); channels last (permute for a network)."""
    return plucker(*pixel_rays(cameras))


@_numpy_in_numpy_out
def plucker_rays_uv(positions: torch.Tensor, centers: torch.Tensor) -> torch.Tensor:
    """UV-space Plucker ray map: positions [..., H, W, 3] a world point per texel (e.g. the posed
    body's UV position map), centers [..., 3] the camera centre(s) seeing them (broadcast over
    the texel grid: positions [R, R, 3] with centers [C, 3] give [C, R, R, 6]) -> [..., H, W, 6]
    (d, o x d) of the ray from the centre through each texel's point. A texel at the centre
    itself gets zeros. numpy in, numpy out."""
    positions, centers = _promote(positions, centers)
    o = centers[..., None, None, :]
    o, p = torch.broadcast_tensors(o, positions)
    return plucker(o, p - o)
