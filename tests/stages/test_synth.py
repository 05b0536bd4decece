"""`dla synth`: deterministic, readable view folders whose images agree with the true body."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from dlacli.cli.app import app
from dlacli.io.motion import read_motion
from dlacli.io.views import read_views
from dlacli.stages.synth import INPUT_AZIMUTHS, POSE_AZIMUTHS, synth

RES = 96
NV, NP = 3, 2


def _digests(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def subjects(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    a = synth(7, root / "a", res=RES, novel_views=NV, novel_poses=NP)
    b = synth(7, root / "b", res=RES, novel_views=NV, novel_poses=NP)
    c = synth(8, root / "c", res=RES, novel_views=NV, novel_poses=NP)
    return a, b, c


def test_same_seed_same_bytes_other_seed_differs(subjects):
    a, b, c = subjects
    da, db, dc = _digests(a), _digests(b), _digests(c)
    assert da == db
    assert set(da) == set(dc)
    assert da["body.json"] != dc["body.json"]
    assert da["images/view_000.png"] != dc["images/view_000.png"]
    assert not any(p.name.startswith(".") for p in a.parent.iterdir())  # no temporary leftovers


def test_folders_read_back(subjects):
    a = subjects[0]
    main = read_views(a)
    assert len(main) == 4 and main.images.shape == (4, RES, RES, 3)
    assert main.times == [None] * 4
    nv = read_views(a / "novel_views")
    assert len(nv) == NV and nv.images.shape[1:3] == (RES, RES)
    npv = read_views(a / "novel_poses")
    assert len(npv) == NP * len(POSE_AZIMUTHS)
    motion = read_motion(a / "novel_poses" / "motion.npz")
    assert motion.num_frames == NP
    assert sorted(set(npv.times)) == list(range(NP))  # every frame's time indexes the motion
    # 4 input views on the documented azimuths: 0 in front (-Y side), 90 on +X
    centres = main.cameras.c2w_opengl()[:, :3, 3]
    az = np.degrees(np.arctan2(centres[:, 0], -centres[:, 1])) % 360.0
    assert np.allclose(az, INPUT_AZIMUTHS, atol=1e-3)
    # novel views are not the input views
    nc = nv.cameras.c2w_opengl()[:, :3, 3]
    naz = np.degrees(np.arctan2(nc[:, 0], -nc[:, 1])) % 360.0
    assert np.min(np.abs((naz[:, None] - np.array(INPUT_AZIMUTHS)[None] + 180) % 360 - 180)) > 4.0
    for vs in (main, nv, npv):
        cover = vs.masks.mean(axis=(1, 2))
        assert np.all(cover > 0.03) and np.all(cover < 0.4), cover
        assert np.all(vs.images[vs.masks == 0] == 0)
        edges = np.concatenate([vs.masks[:, 0], vs.masks[:, -1], vs.masks[:, :, 0], vs.masks[:, :, -1]], 1)
        assert np.all(edges == 0)  # the whole body (feet, head, hands) is in frame


def _project(cameras, points):
    """points [C, P, 3] world -> pixel (x, y) [C, P, 2] and camera depth [C, P]."""
    vm = cameras.viewmats.double().numpy()
    ks = cameras.Ks.double().numpy()
    pc = np.einsum("cij,cpj->cpi", vm[:, :3, :3], points) + vm[:, None, :3, 3]
    uv = np.einsum("cij,cpj->cpi", ks, pc)
    return uv[..., :2] / uv[..., 2:], pc[..., 2]


def _body_inside_alpha(vs, verts_per_view, faces):
    """Fraction of the naked body's silhouette (rendered independently from body.json / motion
    with the read-back cameras) that the subject's alpha covers, per view."""
    from dlacli.render.raster import rasterize

    ras = rasterize(verts_per_view, faces, vs.cameras)
    inside = ras.mask
    return np.array([(vs.masks[k][inside[k]] > 0.5).mean() for k in range(len(vs))])


def test_images_agree_with_the_true_body(subjects):
    from dlacli.body.model import get_body_model

    a = subjects[0]
    model = get_body_model()
    main = read_views(a)
    out = model.forward_body(main.body)
    pelvis = out.bone_heads[0, 0].double().numpy()
    px, depth = _project(main.cameras, np.broadcast_to(pelvis, (4, 1, 3)))
    for k in range(4):
        x, y = np.floor(px[k, 0]).astype(int)
        assert depth[k, 0] > 0 and main.masks[k, y, x] > 0.5
    verts = np.broadcast_to(out.vertices[0].numpy(), (4,) + out.vertices.shape[1:])
    covered = _body_inside_alpha(main, verts, model.faces)
    assert np.all(covered > 0.97), covered

    npv = read_views(a / "novel_poses")
    motion = read_motion(a / "novel_poses" / "motion.npz")
    posed = model.forward_motion(npv.body.phenotype, motion).vertices.numpy()  # [T, V, 3]
    covered = _body_inside_alpha(npv, posed[np.asarray(npv.times)], model.faces)
    assert np.all(covered > 0.97), covered
    # the poses differ from each other and from the input pose
    assert np.abs(posed[0] - posed[1]).max() > 0.05


def test_cli(tmp_path):
    out = tmp_path / "subject"
    res = CliRunner().invoke(app, ["synth", "--seed", "3", "-o", str(out), "--res", "32",
                                   "--novel-views", "0", "--novel-poses", "0"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert res.stdout.strip() == str(out)
    assert sorted(p.name for p in out.iterdir()) == ["body.json", "images", "transforms.json"]


@pytest.mark.parametrize("args, where", [(["--res", "4"], "--res"), (["--seed", "-2"], "--seed"),
                                         (["--novel-views", "-1"], "--novel-views")])  # fmt: skip
def test_bad_arguments(tmp_path, args, where):
    from dlacli.errors import DlaInputError
    from dlacli.stages.synth import synth as run

    kwargs = {"res": 32, "novel_views": 0, "novel_poses": 0, "seed": 1}
    key = args[0].lstrip("-").replace("-", "_")
    kwargs[key] = int(args[1])
    seed = kwargs.pop("seed")
    with pytest.raises(DlaInputError, match=where):
        run(seed, tmp_path / "x", **kwargs)
    assert not (tmp_path / "x").exists()


def test_identical_rendering_of_two_poses_is_not_cached(subjects):
    """Novel-pose images of different frames from the same camera differ (the pose is used)."""
    npv = read_views(subjects[0] / "novel_poses")
    k = len(POSE_AZIMUTHS)
    assert np.abs(npv.masks[0] - npv.masks[k]).max() > 0.5
    assert torch.equal(npv.cameras.viewmats[0], npv.cameras.viewmats[k])


def test_failure_leaves_nothing(tmp_path, monkeypatch):
    import dlacli.stages.synth as st

    def boom(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(st, "novel_motion", boom)  # fails after the input views are written
    with pytest.raises(RuntimeError, match="boom"):
        st.synth(2, tmp_path / "subject", res=32, novel_views=1, novel_poses=1)
    assert list(tmp_path.iterdir()) == []


def test_alpha_matches_an_independent_render_of_the_dressed_mesh(subjects):
    """The layer bias slides vertices along camera rays only, so the alpha equals the coverage
    that dlacli.render.raster.render_mesh computes for the unbiased body + garments mesh."""
    from dlacli.render.raster import render_mesh
    from dlacli.stages.synth import DressedBody, sample_subject

    main = read_views(subjects[0])
    spec = sample_subject(7)
    body = DressedBody(spec)
    verts = body.vertices(spec.rotations[None], torch.zeros(1, 3), torch.zeros(1, 3))[0]
    ref = render_mesh(verts, body.faces, np.full((verts.shape[0], 3), 0.5), main.cameras, antialias=2)
    assert np.abs(ref[..., 3] - main.masks).max() <= 0.5 / 255 + 1e-6  # equal up to 8-bit rounding
