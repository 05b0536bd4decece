"""The rounded visual hull (stages/lift/hull.py) against analytic shapes: a round column seen from four
sides, whose true surface the silhouettes' intersection (a square) misses at its corners."""

from __future__ import annotations

import numpy as np
import pytest

from dlacli.geometry import look_at_orbit_cameras
from dlacli.stages.lift.hull import HULL_STEPS, Silhouettes, hull_depth, row_runs
from dlacli.types import ViewSet

RADIUS = 0.3  # metres: the column, a vertical cylinder about the z axis
HALF_HEIGHT = 0.8
DISTANCE = 4.0
SIZE = 256
FOV = 30.0


def _rays(cameras, v: int, cols: np.ndarray, rows: np.ndarray):
    """View v's pixel-centre rays: origin [3], dirs [N, 3] with unit camera-z component."""
    k = cameras.Ks[v].numpy().astype(np.float64)
    c2w = np.linalg.inv(cameras.viewmats[v].numpy().astype(np.float64))
    xc = (cols + 0.5 - k[0, 2]) / k[0, 0]
    yc = (rows + 0.5 - k[1, 2]) / k[1, 1]
    dirs = np.stack([xc, yc, np.ones_like(xc)], -1) @ c2w[:3, :3].T
    return c2w[:3, 3], dirs


def _column_entry(origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Camera-z depth [N] where each ray enters the column (inf where it misses)."""
    o, d = origin[:2], dirs[:, :2]
    a = (d * d).sum(1)
    b = 2.0 * (d @ o)
    c = o @ o - RADIUS**2
    disc = b * b - 4.0 * a * c
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
    z = origin[2] + t * dirs[:, 2]
    return np.where((disc > 0) & (np.abs(z) < HALF_HEIGHT), t, np.inf)


def _column_views() -> ViewSet:
    cameras = look_at_orbit_cameras(np.zeros(3), DISTANCE, [0.0, 90.0, 180.0, 270.0], 0.0, FOV, SIZE)
    rows, cols = np.mgrid[0:SIZE, 0:SIZE]
    masks = np.stack(
        [
            np.isfinite(_column_entry(*_rays(cameras, v, cols.ravel(), rows.ravel()))).reshape(SIZE, SIZE)
            for v in range(4)
        ]
    ).astype(np.float32)
    n = len(masks)
    return ViewSet(np.zeros((n, SIZE, SIZE, 3), np.float32), masks, cameras, None, [""] * n, [None] * n)


def test_row_runs_give_each_mask_pixel_the_centre_and_half_width_of_its_run():
    rng = np.random.default_rng(3)
    mask = rng.random((7, 23)) < 0.6
    centre, half = row_runs(mask)
    for r in range(mask.shape[0]):
        for c in np.flatnonzero(mask[r]):
            start, end = c, c + 1
            while start > 0 and mask[r, start - 1]:
                start -= 1
            while end < mask.shape[1] and mask[r, end]:
                end += 1
            assert centre[r, c] == pytest.approx(0.5 * (start + end))
            assert half[r, c] == pytest.approx(0.5 * (end - start))


def test_the_rounded_hull_finds_a_round_column_where_the_silhouettes_intersection_finds_a_square():
    views = _column_views()
    silhouettes = Silhouettes(views)
    cols = np.flatnonzero(views.masks[0][SIZE // 2] > 0.5)
    rows = np.full(cols.shape, SIZE // 2)
    origin, dirs = _rays(views.cameras, 0, cols, rows)
    box, rounded = hull_depth(origin, dirs, silhouettes, 0, np.zeros(3), RADIUS + 0.4)
    truth = _column_entry(origin, dirs)
    assert np.isfinite(truth).all() and np.isfinite(box).all() and np.isfinite(rounded).all()
    # a pixel here spans this many metres at the column: the masks' resolution bounds both hulls
    pixel = DISTANCE * 2.0 * np.tan(np.radians(FOV / 2)) / SIZE
    lateral = np.abs(origin[0] + dirs[:, 0] * truth)  # |x| where the ray meets the column
    middle, edge = lateral < 0.3 * RADIUS, (lateral > 0.6 * RADIUS) & (lateral < 0.9 * RADIUS)
    assert middle.sum() > 5 and edge.sum() > 5
    # on the axis all three agree; towards the edge the square's face stays in front by
    # r - sqrt(r^2 - x^2) (12 cm at x = 0.8 r) while the rounded hull follows the column
    assert np.abs(rounded - truth)[middle].max() < pixel
    assert np.abs(box - truth)[middle].max() < pixel
    assert np.abs(rounded - truth)[edge].max() < pixel
    assert (truth - box)[edge].min() > 0.3 * RADIUS * (1 - np.sqrt(1 - 0.6**2))
    assert np.all(rounded >= box - 1e-9)  # the rounded hull lies inside the intersection


def test_rays_that_miss_every_silhouette_are_inf_in_both_hulls():
    views = _column_views()
    silhouettes = Silhouettes(views)
    origin, dirs = _rays(views.cameras, 0, np.array([0.0, SIZE / 2]), np.array([SIZE / 2, SIZE / 2]))
    box, rounded = hull_depth(origin, dirs, silhouettes, 0, np.zeros(3), RADIUS + 0.4)
    assert np.isinf(box[0]) and np.isinf(rounded[0])  # the image's left edge: off every silhouette


def test_a_lift_spec_names_its_hull_and_refuses_an_unknown_one():
    from dlacli.errors import DlaInputError
    from dlacli.stages.lift.methods import parse_method
    from dlacli.stages.lift.methods.unproject import HULLS, UnprojectConfig
    from dlacli.stages.lift.unproject import hull_shape

    assert UnprojectConfig().hull is None and set(HULLS) == {"round", "box"}
    assert parse_method("unproject:hull=box").config.hull == "box"
    with pytest.raises(DlaInputError, match="hull must be one of round, box, got cube"):
        parse_method("unproject:hull=cube")

    # unset, the views decide: round for true views, box for a folder dla dream wrote
    views = _column_views()
    assert hull_shape(UnprojectConfig().hull, views) == "round"
    dreamed = ViewSet(views.images, views.masks, views.cameras, None, [""] * 4, [None] * 4, {"dream": {}})
    assert hull_shape(UnprojectConfig().hull, dreamed) == "box"
    assert hull_shape("round", dreamed) == "round"


def test_without_rounding_the_intersection_is_the_same_and_stands_for_both():
    views = _column_views()
    silhouettes = Silhouettes(views)
    cols = np.arange(SIZE // 4, 3 * SIZE // 4)
    origin, dirs = _rays(views.cameras, 0, cols, np.full(cols.shape, SIZE // 2))
    box, _ = hull_depth(origin, dirs, silhouettes, 0, np.zeros(3), RADIUS + 0.4)
    only_box, second = hull_depth(origin, dirs, silhouettes, 0, np.zeros(3), RADIUS + 0.4, rounded=False)
    np.testing.assert_array_equal(second, only_box)  # one result stands for both
    # the same rays marched alone: the projections' products may round otherwise for another
    # row count (BLAS), which can move a sample across a mask edge, by at most one march step
    step = 2.0 * (RADIUS + 0.4) / (HULL_STEPS - 1)
    hit = np.isfinite(box)
    assert 0 < hit.sum() < hit.size  # rays that meet the column and rays beside it
    np.testing.assert_array_equal(np.isfinite(only_box), hit)
    assert np.abs(only_box[hit] - box[hit]).max() <= step
