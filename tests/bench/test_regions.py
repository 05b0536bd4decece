"""Per-region error: labels from the body's own raster, PSNR per region on analytic errors."""

from __future__ import annotations

import numpy as np
import pytest

from dlacli.bench.regions import BAND, REGIONS, error_picture, pixel_regions, region_psnr


@pytest.fixture(scope="module")
def scene():
    from dlacli.body.model import get_body_model
    from dlacli.geometry import look_at_orbit_cameras
    from dlacli.render.raster import rasterize

    m = get_body_model()
    verts = m.rest_vertices()
    cams = look_at_orbit_cameras(np.array([0.0, 0.0, -0.1]), 3.2, [0.0, 90.0], 0.0, 35.0, 128)
    body = (rasterize(verts, m.faces, cams).face_id >= 0).astype(np.float32)
    return verts, cams, body


def test_labels_follow_the_body_and_the_outline(scene):
    from scipy import ndimage

    verts, cams, body = scene
    labels = pixel_regions(verts, cams, body)
    assert np.array_equal(labels >= 0, body > 0.5)  # inside the mask exactly
    band = labels == REGIONS.index("silhouette band")
    for c in range(len(body)):  # the band is the mask less its BAND-pixel erosion
        inner = ndimage.binary_erosion(body[c] > 0.5, iterations=BAND, border_value=0)
        assert np.array_equal(band[c], (body[c] > 0.5) & ~inner)
    assert (labels == REGIONS.index("off body")).sum() == 0  # the mask is the body itself
    front = labels[0]
    assert (front == REGIONS.index("torso")).sum() > (front == REGIONS.index("face")).sum() > 0
    # a mask wider than the body: the extra pixels (away from the outline) are "off body"
    wide = np.stack([ndimage.binary_dilation(b > 0.5, iterations=6) for b in body]).astype(np.float32)
    assert (pixel_regions(verts, cams, wide) == REGIONS.index("off body")).sum() > 0


def test_region_psnr_on_a_known_error(scene):
    verts, cams, body = scene
    labels = pixel_regions(verts, cams, body)
    gt = np.full(body.shape + (3,), 0.5)
    pred = gt.copy()
    torso = labels == REGIONS.index("torso")
    pred[torso] += 0.1  # error 0.1 on the torso only: 20 dB there, inf elsewhere
    out = region_psnr(pred, gt, labels)
    assert out["torso"]["psnr"] == pytest.approx(20.0)
    assert out["torso"]["error"] == pytest.approx(1.0)
    assert out["face"]["psnr"] == float("inf") and out["face"]["error"] == 0.0
    assert sum(r["pixels"] for r in out.values()) == pytest.approx(1.0)
    assert out["torso"]["pixels"] == pytest.approx(torso.sum() / (labels >= 0).sum())
    pic = error_picture(gt[0], pred[0], labels[0])
    assert pic.dtype == np.uint8 and pic.shape[1] == 4 * pic.shape[0]


def test_bench_regions_command(tmp_path, capsys):
    """`dla bench regions` prints one row per region for both splits and writes the picture;
    a non-PNG output is a one-line error."""
    from PIL import Image

    from dlacli.cli.app import main

    with pytest.raises(SystemExit) as info:
        main(["bench", "regions", "--seed", "11", "--steps", "0", "--res", "64", "-o", str(tmp_path / "r.png")])
    out = capsys.readouterr().out
    assert info.value.code == 0
    rows = [line for line in out.splitlines() if line.startswith("| ") and not line.startswith("| region")]
    assert [r.split(" | ")[0][2:] for r in rows] == list(REGIONS)
    assert Image.open(tmp_path / "r.png").size[0] > 0
    with pytest.raises(SystemExit) as info:
        main(["bench", "regions", "-o", str(tmp_path / "r.jpg")])
    assert info.value.code == 2 and "r.jpg" in capsys.readouterr().err
