"""`dla synth`: deterministic, readable view folders whose images agree with the true body; the
"albedo" and "lit" appearances; dataset mode (manifest, resuming, the same files for any --jobs)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from dlacli.cli.app import app
from dlacli.data.cameras import INPUT_AZIMUTHS, POSE_AZIMUTHS
from dlacli.data.synth import synth
from dlacli.errors import DlaInputError
from dlacli.io.motion import read_motion
from dlacli.io.views import read_views

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
    res = CliRunner().invoke(
        app, ["synth", "--seed", "3", "-o", str(out), "--res", "32", "--novel-views", "0", "--novel-poses", "0"]
    )
    assert res.exit_code == 0, res.output
    assert res.stdout.strip() == str(out)
    assert sorted(p.name for p in out.iterdir()) == ["body.json", "images", "transforms.json"]


@pytest.mark.parametrize(
    "args, where", [(["--res", "4"], "--res"), (["--seed", "-2"], "--seed"), (["--novel-views", "-1"], "--novel-views")]
)
def test_bad_arguments(tmp_path, args, where):
    from dlacli.data.synth import synth as run
    from dlacli.errors import DlaInputError

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
    import dlacli.data.poses as poses

    def boom(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(poses, "novel_motion", boom)  # fails after the input views are written
    with pytest.raises(RuntimeError, match="boom"):
        synth(2, tmp_path / "subject", res=32, novel_views=1, novel_poses=1)
    assert list(tmp_path.iterdir()) == []


def test_alpha_matches_an_independent_render_of_the_dressed_mesh(subjects):
    """The layer bias slides vertices along camera rays only, so the alpha equals the coverage
    that dlacli.render.raster.render_mesh computes for the unbiased body + garments mesh."""
    from dlacli.data.garments import DressedBody
    from dlacli.data.subject import sample_subject
    from dlacli.render.raster import render_mesh

    main = read_views(subjects[0])
    spec = sample_subject(7)
    body = DressedBody(spec)
    verts = body.vertices(spec.rotations[None], torch.zeros(1, 3), torch.zeros(1, 3))[0]
    ref = render_mesh(verts, body.faces, np.full((verts.shape[0], 3), 0.5), main.cameras, antialias=2)
    assert np.abs(ref[..., 3] - main.masks).max() <= 0.5 / 255 + 1e-6  # equal up to 8-bit rounding


# ------------------------------------------------------------------------------- appearance


def _static_pixels(body, verts_a, verts_b, cameras, ss: int) -> np.ndarray:
    """[C, H, W] pixels whose every sub-pixel sample sees the same face in both poses, a face
    whose corners and their normals did not change (found with an independent, unbiased z-buffer
    of the two meshes)."""
    from dlacli.render.raster import rasterize
    from dlacli.types import Cameras

    ks = cameras.Ks.clone()
    ks[:, :2, :] *= ss
    hi = Cameras(cameras.viewmats, ks, cameras.width * ss, cameras.height * ss)
    fa = rasterize(verts_a, body.faces, hi).face_id
    fb = rasterize(verts_b, body.faces, hi).face_id
    moved = np.any(verts_a != verts_b, axis=1)[body.faces].any(axis=1)  # [F] a corner moved
    touched = np.zeros(len(verts_a), bool)  # vertices whose normal a moved face changes
    touched[body.faces[moved].ravel()] = True
    still = ~touched[body.faces].any(axis=1)  # [F]
    ok = (fa == fb) & (fa >= 0) & still[np.maximum(fa, 0)]
    c, h, w = len(cameras), cameras.height, cameras.width
    return ok.reshape(c, h, ss, w, ss).all(axis=(2, 4))


def test_lit_colour_follows_the_pose_albedo_does_not():
    """Same subject, same cameras, the arms raised: where the surface did not move, "albedo"
    colours are identical and "lit" ones change (the ambient occlusion of the posed body)."""
    from dlacli.data.appearance import ambient_occlusion, sample_lighting
    from dlacli.data.cameras import INPUT_ELEVATION, synth_orbit_cameras
    from dlacli.data.garments import DressedBody
    from dlacli.data.images import SUPERSAMPLE, render
    from dlacli.data.subject import BonePose, sample_subject

    spec = sample_subject(7)
    body = DressedBody(spec)
    pose = BonePose(body.full.bone_labels, spec.rotations)
    pose.rotate("upperarm01.L", y=-np.radians(75))
    pose.rotate("upperarm01.R", y=np.radians(75))
    verts = body.vertices(np.stack([spec.rotations, pose.rot.astype(np.float32)]), torch.zeros(2, 3), torch.zeros(2, 3))
    cams = synth_orbit_cameras([0.0, 90.0, 270.0], INPUT_ELEVATION, 48)
    light = sample_lighting(7)
    ao = ambient_occlusion(verts, body.faces)  # [2, V]
    still = _static_pixels(body, verts[0], verts[1], cams, SUPERSAMPLE)
    assert still.sum() > 100, still.sum()
    albedo = [render(body, verts[t], cams, 7) for t in range(2)]
    lit = [render(body, verts[t], cams, 7, lighting=light, ao=ao[t]) for t in range(2)]
    assert np.array_equal(albedo[0][still], albedo[1][still])
    diff = np.abs(lit[0] - lit[1])[still][:, :3].max(axis=1)
    assert diff.max() > 0.03 and (diff > 2 / 255).sum() > 10, (diff.max(), (diff > 2 / 255).sum())
    # and the raised arm un-shadows the torso: the mean ambient occlusion of the still vertices rises
    moved = np.any(verts[0] != verts[1], axis=1)
    used = np.zeros(len(moved), bool)
    used[body.faces] = True
    assert ao[1][used & ~moved].mean() > ao[0][used & ~moved].mean()


def test_lights_that_turn_with_the_camera():
    """`light_view`: every camera sees the lights as the camera `light_view` is the rotation of.
    Oracle: camera B with light_view R_A is world-lit with the lights turned by R_B^T R_A (what
    B would see if the world's lights were those), and camera A itself is unchanged."""
    import dataclasses

    from dlacli.data.appearance import ambient_occlusion, sample_lighting
    from dlacli.data.cameras import INPUT_ELEVATION, synth_orbit_cameras
    from dlacli.data.garments import DressedBody
    from dlacli.data.images import render
    from dlacli.data.subject import sample_subject

    spec = sample_subject(11)
    body = DressedBody(spec)
    verts = body.vertices(spec.rotations[None], torch.zeros(1, 3), torch.zeros(1, 3))[0]
    cams = synth_orbit_cameras([0.0, 135.0], INPUT_ELEVATION, 48)
    light, ao = sample_lighting(11), ambient_occlusion(verts, body.faces)
    r = cams.viewmats[:, :3, :3].double().numpy()
    world = render(body, verts, cams, 11, lighting=light, ao=ao)
    turned = render(body, verts, cams, 11, lighting=light, ao=ao, light_view=r[0])
    assert np.array_equal(turned[0], world[0])
    moved = dataclasses.replace(light, directions=light.directions @ (r[1].T @ r[0]).T)
    oracle = render(body, verts, cams.select(1), 11, lighting=moved, ao=ao)[0]
    assert np.allclose(turned[1], oracle, atol=1e-6)
    assert np.abs(turned[1] - world[1]).max() > 0.05  # the lights did turn


def test_specular_depends_on_the_view_diffuse_does_not():
    """lit_terms of the same surface points seen from two eyes: equal diffuse, other specular;
    Blinn-Phong's peak (eye on the mirror direction) is the material's strength x light colour."""
    from dlacli.data.appearance import SPECULAR, Lighting, lit_terms, sample_lighting
    from dlacli.data.garments import MATERIALS

    rng = np.random.default_rng(0)
    light = sample_lighting(3)
    n = rng.normal(size=(200, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    mats = rng.choice([MATERIALS.index(m) for m in ("skin", "hair", "shoes")], 200)
    ao = rng.uniform(0.3, 1.0, 200)
    eyes = [n + 0.6 * rng.normal(size=(200, 3)), n + 0.6 * rng.normal(size=(200, 3))]
    eyes = [e / np.linalg.norm(e, axis=1, keepdims=True) for e in eyes]
    eyes = [e * np.sign((e * n).sum(1, keepdims=True)) for e in eyes]  # both on the side the normal faces
    (d1, s1), (d2, s2) = (lit_terms(mats, n, e, ao, light) for e in eyes)
    np.testing.assert_array_equal(d1, d2)
    assert np.abs(s1 - s2).max() > 0.05
    # the peak: one light, normal = its direction, eye on the mirror direction (here: the normal too)
    one = Lighting(0.0, light.directions[:1], light.colours[:1])
    for m in ("skin", "hair", "shoes", "suit", "eyes"):
        d = light.directions[:1]
        diffuse, spec = lit_terms(np.array([MATERIALS.index(m)]), d, d, np.zeros(1), one)
        np.testing.assert_allclose(spec[0], SPECULAR[m][0] * light.colours[0], rtol=1e-12)
        np.testing.assert_allclose(diffuse[0], light.colours[0], rtol=1e-12)  # n.l = 1, no ambient


def _grid(x0, x1, y0, y1, step, to3d):
    """A flat grid mesh: vertices to3d(u, v) [N, 3], faces [F, 3] (counter-clockwise in u, v)."""
    us, vs = np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    verts = to3d(uu.ravel(), vv.ravel())
    nu, nv = len(us), len(vs)
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return verts, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def test_ambient_occlusion_against_analytic_scenes():
    from dlacli.data.appearance import AO_DIRECTIONS, ambient_occlusion, sphere_directions

    # a convex body occludes nothing of itself: a UV sphere has AO 1 everywhere
    th, ph = np.meshgrid(
        np.linspace(0.05, np.pi - 0.05, 24), np.linspace(0, 2 * np.pi, 48, endpoint=False), indexing="ij"
    )
    sphere = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3) * 0.4
    idx = np.arange(24 * 48).reshape(24, 48)
    a, b = idx[:-1], np.roll(idx, -1, axis=1)[:-1]
    c, d = np.roll(idx, -1, axis=1)[1:], idx[1:]
    faces = np.concatenate([np.stack([a, d, c], -1).reshape(-1, 3), np.stack([a, c, b], -1).reshape(-1, 3)])
    assert ambient_occlusion(sphere, faces).min() > 0.97
    # a floor (z = 0, facing up) beside a wall (x = 0, 4 m high, 8 m wide, facing +x): the floor
    # points' AO is the cosine-weighted share of the sampled directions whose ray misses the wall
    floor, ff = _grid(-4, 4, -4, 4, 0.5, lambda u, v: np.stack([u, v, 0 * u], 1))
    wall, wf = _grid(-4, 4, 0, 4, 0.5, lambda u, v: np.stack([0 * u, u, v], 1))
    verts = np.concatenate([floor, wall])
    faces = np.concatenate([ff, wf[:, ::-1] + len(floor)])
    ao = ambient_occlusion(verts, faces)
    dirs = sphere_directions(AO_DIRECTIONS)
    for x in (0.5, 1.0, 3.0):
        k = int(np.argmin(np.linalg.norm(floor - [x, 0.5, 0.0], axis=1)))
        p = floor[k]
        up = dirs[:, 2] > 0
        s = -p[0] / np.minimum(dirs[:, 0], -1e-12)  # ray length to the wall's plane (toward -x only)
        hy, hz = p[1] + s * dirs[:, 1], s * dirs[:, 2]
        blocked = (dirs[:, 0] < 0) & (np.abs(hy) <= 4) & (hz <= 4)
        w = np.where(up, dirs[:, 2], 0.0)
        expect = (w * ~blocked).sum() / w.sum()
        assert abs(ao[k] - expect) < 0.05, (x, ao[k], expect)
    near, far = (int(np.argmin(np.linalg.norm(floor - [x, 0.5, 0.0], axis=1))) for x in (0.5, 3.0))
    assert ao[near] < ao[far] < 1.0


def test_albedo_is_the_headlight_formula():
    """The default appearance: colour = albedo x (0.35 + 0.65 |cos(normal, view ray)|) per
    sub-pixel of the layer-biased z-buffer (docs/synth.md), averaged; checked where alpha = 1."""
    from dlacli.data.appearance import shade_colors
    from dlacli.data.cameras import INPUT_AZIMUTHS, INPUT_ELEVATION, synth_orbit_cameras
    from dlacli.data.garments import DressedBody
    from dlacli.data.images import render
    from dlacli.data.subject import sample_subject
    from dlacli.render.raster import interpolate, rasterize_camera_space, vertex_normals, world_to_camera

    spec = sample_subject(3)
    body = DressedBody(spec)
    verts = body.vertices(spec.rotations[None], torch.zeros(1, 3), torch.zeros(1, 3))[0]
    cams = synth_orbit_cameras(INPUT_AZIMUTHS, INPUT_ELEVATION, 32)
    ours = render(body, verts, cams, 3)
    ss, res = 2, 32
    for k in range(4):
        vcam = world_to_camera(verts, cams.viewmats[k : k + 1].double().numpy())[0]  # [V, 3]
        slid = vcam * (1.0 - body.depth_bias[:, None] / np.linalg.norm(vcam, axis=1, keepdims=True))
        ks = cams.Ks[k].double().numpy().copy()
        ks[:2] *= ss
        ras = rasterize_camera_space(slid, body.faces, ks, res * ss, res * ss)
        fid = ras.face_id[0]
        cov = fid >= 0
        f, bary = fid[cov], ras.bary[0][cov].astype(np.float64)
        pos = interpolate(vcam, body.faces, fid[None], ras.bary[0][None])[0][cov]
        nrm = interpolate(vertex_normals(vcam, body.faces), body.faces, fid[None], ras.bary[0][None])[0][cov]
        rest = np.einsum("nk,nkd->nd", bary, body.rest[body.faces[f]])
        uv = np.einsum("nk,nkd->nd", bary, body.face_uv[f])
        cos = np.abs((nrm * pos).sum(1)) / (np.linalg.norm(nrm, axis=1) * np.linalg.norm(pos, axis=1))
        sub = np.zeros((res * ss, res * ss, 3))
        sub[cov] = shade_colors(body, body.face_material[f], rest, uv, 3) * (0.35 + 0.65 * cos)[:, None]
        full = cov.reshape(res, ss, res, ss).all(axis=(1, 3))
        expect = sub.reshape(res, ss, res, ss, 3).mean(axis=(1, 3))
        assert full.sum() > 20
        np.testing.assert_allclose(ours[k][full][:, :3], expect[full], rtol=0, atol=1e-5)
        assert np.all(ours[k][full][:, 3] == 1.0)


def test_wardrobes():
    """ "default" is the documented outfit rule; "full" keeps the phenotype and pose of the seed
    and draws every kind from the shipped garments."""
    from dlacli.body.garments import GARMENT_KIND
    from dlacli.data.subject import HAIRS, SHOES, SUITS_FEMALE, SUITS_MALE, sample_subject

    assert set(SUITS_FEMALE + SUITS_MALE + SHOES + HAIRS) == set(GARMENT_KIND)
    for seed in (0, 1, 2):
        d, f = sample_subject(seed), sample_subject(seed, "full")
        suit = "female_casualsuit01" if d.phenotype["gender"] >= 0.5 else "male_casualsuit01"
        assert d.outfit == (suit, "shoes01", "short02")
        assert f.phenotype == d.phenotype and np.array_equal(f.rotations, d.rotations)
        assert [GARMENT_KIND[g] for g in f.outfit] == ["suit", "shoes", "hair"]
    with pytest.raises(DlaInputError, match="--wardrobe"):
        sample_subject(0, "fancy")


# ------------------------------------------------------------------------------- dataset mode

DATA_ARGS = ["--res", "32", "--novel-views", "1", "--novel-poses", "2"]


def _write_dataset(folder: Path, clip: Path, jobs: int):
    args = ["synth", "--seeds", "4-5", "-o", str(folder), *DATA_ARGS, "--motions", str(clip), "--jobs", str(jobs)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return folder, res


@pytest.fixture(scope="module")
def datasets(tmp_path_factory, third_party_data):
    """A 2-subject dataset written by --jobs 1 (a CMU clip among the motions)."""
    clip = third_party_data / "motion" / "131_01.bvh"
    return {1: _write_dataset(tmp_path_factory.mktemp("datasets") / "j1", clip, 1)}, clip


def _dla(argv, capsys) -> tuple[int, str, str]:
    """The console entry point (one-line errors, exit code 2) -> (code, stdout, stderr)."""
    from dlacli.cli.app import main

    with pytest.raises(SystemExit) as info:
        main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return info.value.code, out, err


def _subject_digests(root: Path) -> dict[str, str]:
    return {k: v for k, v in _digests(root).items() if k != "manifest.json"}


def test_dataset_same_files_for_any_jobs(datasets, tmp_path):
    (a, res), clip = datasets[0][1], datasets[1]
    b, _ = _write_dataset(tmp_path / "j2", clip, 2)  # two worker processes (spawned)
    assert res.stdout.strip() == str(a)
    assert "subject_4:" in res.stderr and "subject_5:" in res.stderr  # one progress line per subject
    da, db = _subject_digests(a), _subject_digests(b)
    assert da == db and len(da) > 20
    assert sorted(p.name for p in a.iterdir()) == ["manifest.json", "subject_4", "subject_5"]


def test_dataset_manifest(datasets):
    from dlacli.data.dataset import read_manifest

    (a, _), clip = datasets[0][1], datasets[1]
    m = read_manifest(a / "manifest.json")
    assert m["format"] == "dla.dataset/1"
    assert [(e["seed"], e["path"]) for e in m["subjects"]] == [(4, "subject_4"), (5, "subject_5")]
    s = m["settings"]
    assert (s["res"], s["novel_views"], s["novel_poses"], s["appearance"], s["wardrobe"]) == (32, 1, 2, "lit", "full")
    assert s["motion_files"] == [{"name": "131_01.bvh", "sha256": hashlib.sha256(clip.read_bytes()).hexdigest()}]
    for e in m["subjects"]:
        size = sum(p.stat().st_size for p in (a / e["path"]).rglob("*") if p.is_file())
        assert e["bytes"] == size and e["seconds"] > 0 and e["appearance"] == "lit"
        info = read_views(a / e["path"]).extra["synth"]
        assert e["outfit"] == info["outfit"] and info["lighting"]["lights"]
    assert m["bytes_per_subject"] == int(np.mean([e["bytes"] for e in m["subjects"]]))
    assert m["seconds_per_subject"] == pytest.approx(np.mean([e["seconds"] for e in m["subjects"]]), abs=1e-3)


def test_dataset_cameras_and_target_poses(datasets):
    """Input cameras 90 degrees apart from the recorded random start yaw, elevations jittered
    around INPUT_ELEVATION; clip frames among the target poses have the root above the origin."""
    from dlacli.data.appearance import sample_lighting
    from dlacli.data.cameras import ELEVATION_JITTER, INPUT_ELEVATION, TARGET

    a = datasets[0][1][0]
    yaws = []
    for seed in (4, 5):
        main = read_views(a / f"subject_{seed}")
        info = main.extra["synth"]
        eye = main.cameras.c2w_opengl()[:, :3, 3] - np.asarray(TARGET)
        az = np.degrees(np.arctan2(eye[:, 0], -eye[:, 1])) % 360.0
        el = np.degrees(np.arcsin(eye[:, 2] / np.linalg.norm(eye, axis=1)))
        expect = (info["start_yaw"] + np.array(INPUT_AZIMUTHS)) % 360.0
        assert np.allclose((az - expect + 180) % 360 - 180, 0, atol=1e-3)
        assert np.allclose(el, info["elevations"], atol=1e-3)
        assert np.all(np.abs(el - INPUT_ELEVATION) <= ELEVATION_JITTER) and np.ptp(el) > 0
        assert info["lighting"] == sample_lighting(seed).as_dict()
        yaws.append(info["start_yaw"])
        npv = read_views(a / f"subject_{seed}" / "novel_poses", require_body=False)
        motion = read_motion(a / f"subject_{seed}" / "novel_poses" / "motion.npz")
        kinds = npv.extra["pose_kinds"]
        assert "@" in kinds[0] and kinds[1] == "arms_raised"  # a clip frame, then novel_motion's first kind
        assert np.all(motion.root_translation[0, :2] == 0)
    assert abs(yaws[0] - yaws[1]) > 1e-3


def test_dataset_resumes_and_refuses_other_settings(datasets, tmp_path, capsys):
    (a, _), clip = datasets[0][1], datasets[1]
    before = {p.name: p.stat().st_mtime_ns for p in a.iterdir()}
    digests = _subject_digests(a)
    code, _, err = _dla(["synth", "--seeds", "4-5", "-o", a, *DATA_ARGS, "--motions", clip], capsys)
    assert code == 0 and "0 subjects to write, 2 already complete" in err
    after = {p.name: p.stat().st_mtime_ns for p in a.iterdir()}
    assert all(after[k] == before[k] for k in ("subject_4", "subject_5")) and _subject_digests(a) == digests
    # other settings for the same folder: one line, exit 2, nothing written
    code, _, err = _dla(["synth", "--seeds", "4-6", "-o", a, *DATA_ARGS], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert lines[0].startswith(f"error: {a / 'manifest.json'}: was written with other settings")
    assert "motion_files" in lines[0]
    assert not (a / "subject_6").exists()
    # folders that are not datasets: a user's file in it, or no manifest
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("mine")
    code, _, err = _dla(["synth", "--seeds", "1", "-o", tmp_path / "junk", *DATA_ARGS], capsys)
    assert code == 2 and "did not write there (notes.txt)" in err and (tmp_path / "junk" / "notes.txt").exists()
    (tmp_path / "bare" / "subject_1").mkdir(parents=True)
    code, _, err = _dla(["synth", "--seeds", "1", "-o", tmp_path / "bare", *DATA_ARGS], capsys)
    assert code == 2 and "holds no manifest.json: not a dla dataset folder" in err


@pytest.mark.parametrize(
    "args, problem",
    [
        (["--seed", "1", "--seeds", "1-2"], "exactly one"),
        ([], "exactly one"),
        (["--seeds", "5-2"], "must be 0 <= A <= B"),
        (["--seeds", "1,1"], "twice"),
        (["--seeds", "x"], "expected A-B"),
        (["--seed", "1", "--jobs", "2"], "dataset mode"),
        (["--seed", "1", "--appearance", "glossy"], "--appearance"),
        (["--seeds", "1", "--wardrobe", "fancy"], "--wardrobe"),
        (["--seeds", "1", "--motions", "nowhere.bvh"], "nowhere.bvh"),
    ],
)
def test_cli_mode_errors(tmp_path, capsys, args, problem):
    code, _, err = _dla(["synth", "-o", tmp_path / "x", "--res", "16", *args], capsys)
    assert code == 2 and problem in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "x").exists()


def test_train_and_heldout_wardrobes_split_the_garments():
    from dlacli.data.subject import HELD_OUT, sample_subject

    for seed in range(40):
        full = sample_subject(seed, "full")
        train = sample_subject(seed, "train")
        held = sample_subject(seed, "heldout")
        assert not set(train.outfit) & set(HELD_OUT)
        suit, shoes, hair = held.outfit
        assert suit in HELD_OUT and hair in HELD_OUT and shoes not in HELD_OUT
        assert train.phenotype == full.phenotype == held.phenotype
        np.testing.assert_array_equal(train.rotations, full.rotations)
