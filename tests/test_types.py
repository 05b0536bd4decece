"""types.Cameras: `resized` (the one camera rescaling) against projection, and `select`."""

from __future__ import annotations

import numpy as np
import torch

from dlacli.geometry import look_at_orbit_cameras, project_points
from dlacli.types import Cameras


def _cameras() -> Cameras:
    cams = look_at_orbit_cameras(np.zeros(3), 3.0, np.array([0.0, 70.0, 200.0]), 10.0, 40.0, 64)
    ks = cams.Ks.clone()
    ks[:, 0, 2] += 3.0  # an off-centre principal point and a wider image
    return Cameras(cams.viewmats, ks, 80, 64)


def _pixels(cams: Cameras, points: np.ndarray) -> np.ndarray:
    w2c, ks = cams.viewmats.double().numpy(), cams.Ks.double().numpy()
    return np.stack([project_points(points, w2c[c], ks[c])[0] for c in range(len(cams))])


def test_resized_keeps_the_field_of_view():
    """A point at continuous pixel (u, v) (pixel centres at +0.5) of a W x H image lands at
    (u W'/W, v H'/H) in the W' x H' image: same field of view, pixel edges onto pixel edges."""
    cams = _cameras()
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (20, 3))
    small = cams.resized(20, 48)
    assert (small.width, small.height) == (20, 48) and len(small) == 3
    np.testing.assert_allclose(_pixels(small, points), _pixels(cams, points) * [20 / 80, 48 / 64], rtol=1e-5)
    assert torch.equal(small.viewmats, cams.viewmats) and small.viewmats is not cams.viewmats
    assert torch.equal(cams.Ks, _cameras().Ks)  # the original is untouched


def test_resized_with_a_scale_crops():
    """Blocks of 3 pixels with the remainder cropped: both rows scale by 1/3, the size is what the
    blocks cover; a pixel edge at 3k maps to k."""
    cams = _cameras()
    crop = cams.resized(80 // 3, 64 // 3, scale=1.0 / 3)
    assert (crop.width, crop.height) == (26, 21)
    want = cams.Ks.clone()
    want[:, :2, :] *= 1.0 / 3
    assert torch.equal(crop.Ks, want)


def test_select_keeps_the_batch_axis():
    cams = _cameras()
    for index in (1, np.int64(1), slice(1, 2), [1], np.array([1]), torch.tensor([1])):
        one = cams.select(index)
        assert len(one) == 1 and torch.equal(one.viewmats[0], cams.viewmats[1]) and torch.equal(one.Ks[0], cams.Ks[1])
    assert len(cams.select([2, 0])) == 2 and (cams.select([2, 0]).width, cams.select(0).height) == (80, 64)
