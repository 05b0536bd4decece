"""UV regions: a partition of the covered texels, on the right side of the body, agreeing with
anny's own part segmentation; and the `dla body regions` command."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image
from typer.testing import CliRunner

from dlacli.body import regions as Rg
from dlacli.body.model import get_body_model
from dlacli.body.uv import position_map, uv_raster
from dlacli.errors import DlaInputError

RES = 256


@pytest.fixture(scope="module")
def body():
    return get_body_model()


@pytest.fixture(scope="module")
def rest_pmap(body):
    return position_map(torch.from_numpy(body.rest_vertices()), RES).numpy()  # [R, R, 3]


def test_parts_partition_covered_texels():
    valid = uv_raster(RES).mask
    count = sum(Rg.region_mask(p, RES).astype(int) for p in Rg.PARTS)
    assert np.all(count[valid] == 1) and np.all(count[~valid] == 0)
    for p in Rg.PARTS:
        assert Rg.region_mask(p, RES).sum() > 50, p
    upper, lower = Rg.region_mask("upper_body", RES), Rg.region_mask("lower_body", RES)
    assert np.all((upper ^ lower) == valid)
    onehot = Rg.segmentation_onehot(RES)
    assert onehot.shape == (len(Rg.PARTS), RES, RES)
    np.testing.assert_array_equal(onehot.sum(0), valid.astype(np.float32))


def test_composites_are_unions():
    m = lambda n: Rg.region_mask(n, RES)  # noqa: E731
    np.testing.assert_array_equal(m("head"), m("face") | m("hair"))
    np.testing.assert_array_equal(m("hands"), m("left_hand") | m("right_hand"))
    np.testing.assert_array_equal(m("feet"), m("left_foot") | m("right_foot"))
    np.testing.assert_array_equal(m("arms"), m("left_arm") | m("right_arm"))
    np.testing.assert_array_equal(m("legs"), m("left_leg") | m("right_leg"))
    assert not (m("legs") & m("upper_body")).any() and not (m("head") & m("lower_body")).any()
    assert (m("torso") & m("lower_body")).any() and (m("torso") & m("upper_body")).any()
    for name in Rg.REGION_NAMES:
        assert Rg.region_mask(name, 64).shape == (64, 64)


def test_unknown_region_lists_valid_names():
    with pytest.raises(DlaInputError) as err:
        Rg.region_mask("elbow", RES)
    assert "unknown region 'elbow'" in str(err.value) and "left_hand" in str(err.value)


def test_left_is_plus_x_and_parts_sit_where_expected(body, rest_pmap):
    def centre(name):
        return rest_pmap[Rg.region_mask(name, RES)].mean(0)

    for part in ("hand", "foot", "arm", "leg"):
        assert centre(f"left_{part}")[0] > 0.05 > -0.05 > centre(f"right_{part}")[0], part
    heads = body.rest_bone_heads()
    head_bone = heads[body.bone_labels.index("head")]
    assert centre("face")[1] < head_bone[1] < centre("hair")[1]  # face in front (-Y), hair behind
    assert centre("hair")[2] > centre("face")[2] > centre("torso")[2] > centre("legs")[2] > centre("feet")[2]
    # the lower body stays below the chest, the head above the collar bones
    assert rest_pmap[Rg.region_mask("lower_body", RES)][:, 2].max() < heads[body.bone_labels.index("spine01"), 2]
    assert rest_pmap[Rg.region_mask("head", RES)][:, 2].min() > heads[body.bone_labels.index("clavicle.L"), 2]


def test_hands_and_feet_agree_with_anny_segmentation(body):
    """anny's own face-segmentation helper (rounding its own way, exact colours) as the oracle."""
    from anny.face_segmentation import get_face_segmentation_mask

    class _Layout:  # the attributes anny's helper reads
        texture_coordinates = torch.from_numpy(body.uv.astype(np.float64))
        face_texture_coordinate_indices = torch.from_numpy(body.face_uv)
        faces = body.faces
        device = torch.device("cpu")

    for ours, theirs in (
        ("left_hand", "hand.L"),
        ("right_hand", "hand.R"),
        ("left_foot", "foot.L"),
        ("right_foot", "foot.R"),
    ):
        ref = get_face_segmentation_mask(_Layout, [theirs]).numpy()
        mine = Rg.region_faces(ours)
        assert ref.sum() > 100
        agree = (ref & mine).sum() / (ref | mine).sum()
        assert agree > 0.98, (ours, agree)
    head_labels = ["head", "mouth_cavity", "tongue"] + [
        f"eye_{k}.{s}" for k in ("back", "front", "cavity") for s in "LR"
    ]
    ref_head = get_face_segmentation_mask(_Layout, head_labels).numpy()
    assert (Rg.region_faces("head") & ~ref_head).sum() < 0.01 * ref_head.sum()


def test_cli_draws_regions(tmp_path):
    from dlacli.cli.app import app
    from dlacli.cli.body import _PART_COLORS

    out = tmp_path / "regions.png"
    result = CliRunner().invoke(app, ["body", "regions", "-o", str(out), "--res", "128"])
    assert result.exit_code == 0, result.output
    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape[1] > img.shape[0] >= 128  # the UV map plus a legend beside it
    uv_part = img[:128, :128].reshape(-1, 3)
    colours = {tuple(c) for c in uv_part}
    for name in ("face", "hair", "left_hand"):
        assert _PART_COLORS[name] in colours, name
    dark_foot = tuple(int(c * 0.7) for c in _PART_COLORS["right_foot"])  # lower body is darkened
    assert dark_foot in colours
    bad = CliRunner().invoke(app, ["body", "regions", "-o", str(tmp_path / "r.jpg")])
    assert isinstance(bad.exception, DlaInputError) and not (tmp_path / "r.jpg").exists()
