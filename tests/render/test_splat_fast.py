"""The fast compositing kernel (`render_gaussians(exact=False)`, fast_kernels.raster_forward_fast)
against the exact kernel, which stays the reference.

Oracles: float64 `np.exp` for its exponential; the exact path's images of a held-out avatar (a
synthetic subject on a reserved seed, lifted by unprojection, posed with the built-in walk) and
of a random dense scene. What the tolerance follows from: each alpha is off by at most
FAST_EXP_REL_ERROR of itself plus float32 rounding of sigma and of the state (~1e-6 relative), so
a pixel's colour moves by ~1e-5 at most, except where a Gaussian's alpha lies within that
relative distance of the 1/255 cut or a pixel's transmittance of the 1e-4 stop: there one
Gaussian of alpha ~1/255 (or a remainder below 1e-4) comes or goes, a change below 1.1/255 of
the pixel. Such pixels are rare (measured: none above 1e-3 in most frames).
"""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from dlacli.render import fast_kernels as K
from dlacli.render.splat import render_gaussians

FLIP = 1.1 / 255.0  # one Gaussian at the alpha cut, or the remainder under the stop rule


def test_the_fast_exponential_is_within_its_stated_error():
    s = np.linspace(0.0, 5.6, 2_000_001).astype(np.float32)
    got = K._exp_neg_fast(s).astype(np.float64)
    want = np.exp(-s.astype(np.float64))
    assert np.max(np.abs(got - want) / want) < K.FAST_EXP_REL_ERROR
    tail = np.linspace(5.6, K.FAST_SIGMA_MAX, 10_001).astype(np.float32)  # below the cut, still close
    assert np.max(np.abs(K._exp_neg_fast(tail) - np.exp(-tail.astype(np.float64)))) < 1e-7


def _compare(g, cams, mean_tol=2e-6):
    with torch.no_grad():
        exact = render_gaussians(g, cams)
        fast = render_gaussians(g, cams, exact=False)
    for name, a, b in zip(("rgb", "alpha"), fast, exact):
        d = (a.double() - b.double()).abs()
        assert d.max() < FLIP, (name, float(d.max()))
        assert d.mean() < mean_tol, (name, float(d.mean()))
        assert (d > 1e-3).double().mean() < 1e-3, name  # the flips are rare
    return exact, fast


@pytest.fixture(scope="module")
def walking_avatar(tmp_path_factory):
    """A held-out subject (reserved seed, held-out garments), unprojected at 512 px, posed for a
    few walk frames at 131,072 Gaussians, with the preview's following cameras."""
    from dlacli.body.builtin_motions import builtin_motion
    from dlacli.data.synth import synth
    from dlacli.io.views import read_views
    from dlacli.stages.animate import follow_cameras, pose_avatar
    from dlacli.stages.lift.methods import make_spec
    from dlacli.types import Motion

    folder = synth(
        9007, tmp_path_factory.mktemp("fast") / "s", res=256, novel_views=0, novel_poses=0, wardrobe="heldout"
    )
    avatar = make_spec("unproject", steps=0).lift(read_views(folder)).avatar
    walk = builtin_motion("walk")
    idx = np.arange(0, walk.num_frames, max(1, walk.num_frames // 4))[:4]
    clip = Motion(walk.bone_labels, walk.rotations[idx], walk.root_rotation[idx], walk.root_translation[idx], walk.fps)
    anim = pose_avatar(avatar, clip, 131072)
    return anim, follow_cameras(anim.pelvis, anim.fps, 320)


def test_the_fast_kernel_draws_the_exact_images_of_a_held_out_avatar(walking_avatar):
    anim, cams = walking_avatar
    for t in range(anim.num_frames):
        exact, _ = _compare(anim.frame(t), cams.select(t))
        assert exact.alpha.max() > 0.99 and (exact.alpha == 0).any()  # a person, and background


def test_the_fast_kernel_draws_the_exact_images_of_a_dense_random_scene():
    from tests.render.test_splat import look_at_cameras, random_gaussians

    g = random_gaussians(3000, 0, seed=11, extent=1.2, scale=(0.005, 0.08)).to(torch.float32)
    cams = look_at_cameras([(0.5, -2.6, 0.6), (-2.4, 0.9, -0.2)], 97, 75, 80.0, dtype=torch.float32)
    exact, _ = _compare(g, cams, mean_tol=1e-5)
    assert (exact.alpha < 1e-3).any() and exact.alpha.max() > 0.99


def test_narrow_gaussians_at_every_place_in_a_tile_are_drawn_whole():
    # the fast kernel evaluates a box under K.HALF pixels wide on HALF pixels from its first (moved
    # left where it would leave the tile): sparse small Gaussians put such boxes at every column
    # of a tile, at its right end too, beside wider ones; every pixel must match the exact kernel
    from tests.render.test_splat import look_at_cameras, random_gaussians

    from dlacli.render import binning_kernels as B
    from dlacli.render.splat import binned_plain

    g = random_gaussians(600, 0, seed=5, extent=1.0, scale=(0.002, 0.03)).to(torch.float32)
    cams = look_at_cameras([(0.3, -2.5, 0.2)], 160, 128, 150.0, dtype=torch.float32)
    exact, _ = _compare(g, cams)
    params, _, _ = binned_plain(g, cams.viewmats, cams.Ks, 160, 128, 0)
    drawn = params[:, 6] > 0  # culled rows are left unset: only the pairs with a cut-off
    x0, x1 = params[drawn, 7].astype(int), params[drawn, 8].astype(int)
    starts, wide = set(), False
    for a, b in zip(x0, x1):  # each box clipped to the tile columns it spans, as the kernel sees it
        for tx in range(a // B.TILE, b // B.TILE + 1):
            lo, hi = max(a, tx * B.TILE) - tx * B.TILE, min(b, tx * B.TILE + B.TILE - 1) - tx * B.TILE
            starts |= {lo} if hi - lo < K.HALF else set()
            wide |= hi - lo >= K.HALF
    assert starts == set(range(B.TILE)) and wide  # narrow boxes start at every column; wider ones too
    assert exact.alpha.max() > 0.5


def test_the_fast_kernel_gives_the_same_bits_run_to_run_and_for_1_or_2_threads(walking_avatar):
    anim, cams = walking_avatar
    g, cam = anim.frame(1), cams.select(1)
    before = numba.get_num_threads()
    try:
        outs = []
        for threads in (1, 2, 2):
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            with torch.no_grad():
                outs.append(render_gaussians(g, cam, exact=False))
    finally:
        numba.set_num_threads(before)
    for other in outs[1:]:
        for a, b in zip(outs[0], other):
            assert torch.equal(a, b)


def test_exact_false_is_ignored_where_gradients_are_asked_for():
    from tests.render.test_splat import look_at_cameras, random_gaussians, with_grad

    g = with_grad(random_gaussians(60, 0, seed=3).to(torch.float32))
    cams = look_at_cameras([(0.8, -2.4, 0.4)], 33, 27, 30.0, dtype=torch.float32)
    a = render_gaussians(g, cams, exact=False)
    b = render_gaussians(g, cams)
    assert a.rgb.requires_grad and torch.equal(a.rgb, b.rgb)
