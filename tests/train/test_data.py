"""dlacli.train.data: training examples from a synthetic dataset agree with their images, cameras
and bodies, are deterministic for a seeded rng, and bad datasets are one-line errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from dlacli.errors import DlaInputError
from dlacli.train.data import Item, TrainingData, split_subjects


def _settings(root) -> dict:
    return json.loads((root / "manifest.json").read_text())["settings"]


def _project(cameras, points: torch.Tensor) -> np.ndarray:
    """points [C, P, 3] world -> pixel (x, y) [C, P, 2] with a pinhole x = K (R p + t), in float64."""
    vm = cameras.viewmats.double().numpy()
    ks = cameras.Ks.double().numpy()
    p = points.double().numpy()
    cam = np.einsum("cij,cpj->cpi", vm[:, :3, :3], p) + vm[:, None, :3, 3]
    uv = np.einsum("cij,cpj->cpi", ks, cam)
    return uv[..., :2] / uv[..., 2:]


def _inside_fraction(masks: torch.Tensor, pixels: np.ndarray) -> np.ndarray:
    """[C] fraction of the points within one pixel of a pixel with mask > 0.5 (points outside the
    image count as out): at 24-48 px a finger is thinner than a pixel and covers no sample."""
    c, _, h, w = masks.shape
    out = []
    for k in range(c):
        m = np.pad(masks[k, 0].numpy() > 0.5, 1)
        near = np.zeros((h, w), bool)
        for dy in range(3):
            for dx in range(3):
                near |= m[dy : dy + h, dx : dx + w]
        x, y = np.floor(pixels[k, :, 0]).astype(int), np.floor(pixels[k, :, 1]).astype(int)
        ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        hit = np.zeros(x.shape, bool)
        hit[ok] = near[y[ok], x[ok]]
        out.append(hit.mean())
    return np.array(out)


def test_item_shapes_and_kinds(dataset):
    res = _settings(dataset)["res"]
    data = TrainingData(dataset, input_size=res // 2, target_size=res, targets=5)
    assert len(data) == 2 and data.subjects == ["subject_21", "subject_22"]  # manifest order: by seed
    item = data.item(0, np.random.default_rng(0))
    assert isinstance(item, Item) and item.subject == "subject_21"
    s, h, v = res // 2, res, item.rest_vertices.shape[0]
    assert item.input_rgb.shape == (4, 3, s, s) and item.input_mask.shape == (4, 1, s, s)
    assert item.target_rgb.shape == (5, 3, h, h) and item.target_mask.shape == (5, 1, h, h)
    assert item.input_vertices.shape == (v, 3) and item.target_vertices.shape == (5, v, 3)
    assert len(item.input_cameras) == 4 and item.input_cameras.width == s
    assert len(item.target_cameras) == 5 and item.target_cameras.height == h
    for t in (item.input_rgb, item.input_mask, item.target_rgb, item.target_vertices, item.rest_vertices):
        assert t.dtype == torch.float32 and t.device.type == "cpu"
    assert set(item.target_kind) <= {"view", "pose"}
    # black background: no colour where there is no person
    assert torch.all(item.input_rgb[item.input_mask.expand_as(item.input_rgb) == 0] == 0)
    assert 0.0 <= float(item.target_rgb.min()) and float(item.target_rgb.max()) <= 1.0
    # "view" targets show the input pose, "pose" targets another one
    for k, kind in enumerate(item.target_kind):
        moved = float((item.target_vertices[k] - item.input_vertices).abs().max())
        assert (moved == 0.0) == (kind == "view"), (kind, moved)


def test_target_bodies_project_inside_the_target_masks(dataset):
    """Cameras, poses and images agree: the (naked) body of each target, projected with the
    target's camera, lands inside the (dressed) person's mask; moved sideways it does not."""
    res = _settings(dataset)["res"]
    # native size, then a non-integer downscale (1.5x: 1 px is ~8 cm, so the bar is lower)
    for size, most in ((res, 0.97), (32, 0.85)):
        data = TrainingData(dataset, input_size=size, target_size=size, targets=12)
        for index in range(len(data)):
            item = data.item(index, np.random.default_rng(index))
            inside = _inside_fraction(item.target_mask, _project(item.target_cameras, item.target_vertices))
            assert np.all(inside > most), (size, index, inside)
            posed = item.input_vertices.expand(4, -1, -1)
            inputs = _inside_fraction(item.input_mask, _project(item.input_cameras, posed))
            assert np.all(inputs > most), (size, index, inputs)
            # the negative control: the bodies 0.4 m to each camera's right
            right = item.target_cameras.viewmats[:, 0, :3]  # [T, 3] the camera x axis in the world
            moved = item.target_vertices + 0.4 * right[:, None, :]
            assert np.all(_inside_fraction(item.target_mask, _project(item.target_cameras, moved)) < 0.5)


def _assert_same(a: Item, b: Item) -> None:
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, torch.Tensor):
            assert torch.equal(x, y), name
        elif hasattr(x, "viewmats"):
            assert torch.equal(x.viewmats, y.viewmats) and torch.equal(x.Ks, y.Ks), name
        else:
            assert x == y, name


def test_deterministic_for_a_seeded_rng_with_or_without_cache(dataset):
    data = TrainingData(dataset, input_size=24, target_size=24, targets=6)
    a = data.batch([1, 0], np.random.default_rng(7))
    b = data.batch([1, 0], np.random.default_rng(7))  # from the cache now
    fresh = TrainingData(dataset, input_size=24, target_size=24, targets=6, cache=False)
    c = fresh.batch([1, 0], np.random.default_rng(7))
    for x, y, z in zip(a, b, c):
        _assert_same(x, y)
        _assert_same(x, z)
    assert [i.subject for i in a] == ["subject_22", "subject_21"]
    assert fresh.cached_bytes() == 0 and data.cached_bytes() > 0
    # another rng state draws other targets (the pool holds 2 + 6 + 4 = 12 targets, 6 drawn)
    draws = {tuple(data.item(0, np.random.default_rng(s)).target_cameras.viewmats[:, 0, 3].tolist()) for s in range(4)}
    assert len(draws) > 1


def test_cache_is_bounded(dataset):
    data = TrainingData(dataset, input_size=24, target_size=24, targets=2, max_cached=1)
    data.item(0, np.random.default_rng(0))
    one = data.cached_bytes()
    data.item(1, np.random.default_rng(0))
    assert len(data._cache) == 1 and one > 0
    # the stated memory per subject: 4 S^2 4 + N H^2 4 bytes of images + (1 + M) V 12 of vertices (+ rest)
    v = data.item(0, np.random.default_rng(0)).rest_vertices.shape[0]
    assert one == 4 * 24 * 24 * 4 + 12 * 24 * 24 * 4 + (1 + 2) * v * 12 + v * 12


def test_area_resize_matches_a_block_mean_of_the_png(dataset):
    """Halving the images equals the mean of 2 x 2 blocks of the premultiplied PNG (an oracle
    computed from the file with numpy), up to 8-bit rounding."""
    res = _settings(dataset)["res"]
    item = TrainingData(dataset, input_size=res // 2, target_size=res, targets=1).item(0, np.random.default_rng(0))
    png = np.asarray(Image.open(dataset / "subject_21" / "images" / "view_002.png")).astype(np.float64) / 255.0
    pre = np.concatenate([png[..., :3] * png[..., 3:], png[..., 3:]], axis=-1)
    half = pre.reshape(res // 2, 2, res // 2, 2, 4).mean(axis=(1, 3))
    ours = torch.cat([item.input_rgb[2], item.input_mask[2]]).permute(1, 2, 0).double().numpy()
    assert np.abs(ours - half).max() <= 0.5 / 255.0 + 1e-6


def test_exclude_inputs_and_a_single_subject_folder(dataset):
    data = TrainingData(dataset / "subject_22", input_size=24, target_size=24, targets=30, include_inputs=False)
    assert data.subjects == ["subject_22"]
    item = data.item(0, np.random.default_rng(1))  # 30 > 8 targets: drawn with replacement
    assert item.target_rgb.shape[0] == 30
    inputs = data.item(0, np.random.default_rng(1)).input_cameras.viewmats
    for k in range(30):  # no target is an input camera
        assert not any(torch.equal(item.target_cameras.viewmats[k], inputs[j]) for j in range(4))


def test_split_subjects_by_seed(dataset):
    assert split_subjects(dataset, 1) == (["subject_22"], ["subject_21"])
    assert split_subjects(dataset, 0) == (["subject_21", "subject_22"], [])
    with pytest.raises(DlaInputError, match="validation"):
        split_subjects(dataset, 2)  # nothing would be left to train on
    only = TrainingData(dataset, 24, 24, 1, subjects=split_subjects(dataset, 1)[0])
    assert only.subjects == ["subject_22"]


def test_bad_datasets_name_the_file(dataset, tmp_path):
    with pytest.raises(DlaInputError, match="manifest.json: missing"):
        TrainingData(tmp_path, 24, 24, 1)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "manifest.json").write_text(json.dumps({"format": "dla.dataset/9", "settings": {}, "subjects": []}))
    with pytest.raises(DlaInputError, match=r"bad/manifest.json: format 'dla.dataset/9' is not supported"):
        TrainingData(bad, 24, 24, 1)
    with pytest.raises(DlaInputError, match="has no subject 'subject_99'"):
        TrainingData(dataset, 24, 24, 1, subjects=["subject_99"])
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    shutil.rmtree(copy / "subject_21")
    with pytest.raises(DlaInputError, match="subject_21: missing"):
        TrainingData(copy, 24, 24, 1)
    lost = copy / "subject_22" / "novel_poses" / "images" / "view_004.png"
    lost.unlink()
    data = TrainingData(copy / "subject_22", 24, 24, 1)
    with pytest.raises(DlaInputError) as err:
        data.item(0, np.random.default_rng(0))
    assert str(lost) in str(err.value)
    with pytest.raises(DlaInputError, match="smaller than the requested 96 px"):
        TrainingData(dataset, 96, 24, 1).item(0, np.random.default_rng(0))


# --- hand-made manifests and subject files (no synthetic dataset needed) ----------------------------

EXAMPLE_VIEWS = Path(__file__).resolve().parents[2] / "formats" / "examples" / "views"
GOOD = {"seed": 7, "path": "subject_7", "seconds": 1.5, "bytes": 100}


def _subject(folder: Path, change=None) -> Path:
    """A subject folder: the example view folder, its transforms.json changed by `change(doc)`."""
    shutil.copytree(EXAMPLE_VIEWS, folder)
    if change is not None:
        doc = json.loads((folder / "transforms.json").read_text())
        doc = change(doc) or doc
        (folder / "transforms.json").write_text(json.dumps(doc))
    return folder


def _dataset(root: Path, manifest) -> Path:
    root.mkdir(parents=True)
    _subject(root / "subject_7")
    text = manifest if isinstance(manifest, str) else json.dumps(manifest)
    (root / "manifest.json").write_text(text)
    return root


def _doc(subjects, **top) -> dict:
    return {"format": "dla.dataset/1", "settings": {}, "subjects": subjects, **top}


BAD_MANIFESTS = [
    ("[1, 2]", "is not a JSON object"),
    ('"dla.dataset/1"', "is not a JSON object"),
    (_doc([], settings=[]), "missing the 'settings' object"),
    (_doc({"subject_7": GOOD}), "'subjects' must be a list of objects"),
    (_doc([GOOD, 7]), "subjects[1] must be an object with an integer 'seed' and a 'path', found int"),
    (_doc([{**GOOD, "seed": "7"}]), "subjects[0].seed must be an integer >= 0, found '7'"),
    (_doc([{**GOOD, "seed": True}]), "subjects[0].seed must be an integer >= 0, found True"),
    (_doc([{**GOOD, "seed": -1}]), "subjects[0].seed must be an integer >= 0, found -1"),
    (_doc([{"seed": 7}]), "subjects[0].path must be a folder name, found None"),
    (_doc([{**GOOD, "path": ["subject_7"]}]), "subjects[0].path must be a folder name, found ['subject_7']"),
    (_doc([{**GOOD, "path": "a\x00b"}]), "subjects[0].path must be a folder name, found 'a\\x00b'"),
    (_doc([{**GOOD, "path": ".."}]), "subjects[0].path must be a folder name, found '..'"),
    (_doc([{**GOOD, "path": "../subject_7"}]), "'../subject_7' is not one folder name inside the dataset"),
    (_doc([{**GOOD, "path": "/etc"}]), "'/etc' is not one folder name inside the dataset"),
    (_doc([{**GOOD, "path": "x" * 100_000}]), "(100,000 characters)"),
    (_doc([{**GOOD, "path": "é" * 128}]), "subjects[0].path must be a folder name, found 'ééé"),  # 256 bytes
    (_doc([{**GOOD, "path": "\ud800"}]), "subjects[0].path must be a folder name, found '\\ud800'"),
    (_doc([{**GOOD, "seconds": "slow"}]), "subjects[0].seconds must be null or a number >= 0, found 'slow'"),
    (_doc([{**GOOD, "bytes": 1.5}]), "subjects[0].bytes must be an integer >= 0, found 1.5"),
    (_doc([GOOD, {**GOOD, "path": "subject_8"}]), "subjects[1] repeats the seed 7"),
    (_doc([GOOD, {**GOOD, "seed": 8}]), "subjects[1] repeats the path 'subject_7'"),
]


@pytest.mark.parametrize("manifest, needle", BAD_MANIFESTS)
def test_bad_manifests_are_one_line_errors(tmp_path, manifest, needle):
    """A manifest of the wrong shape or types: one short line naming manifest.json, never an
    AttributeError, KeyError or TypeError, nor a path outside the dataset."""
    from dlacli.data.dataset import read_manifest

    root = _dataset(tmp_path / "data", manifest)
    for read in (lambda: read_manifest(root / "manifest.json"), lambda: TrainingData(root, 24, 24, 1)):
        with pytest.raises(DlaInputError) as err:
            read()
        assert err.value.where == str(root / "manifest.json") and needle in err.value.problem, err.value.problem[:300]
        assert "\n" not in str(err.value) and len(err.value.problem) < 200, err.value.problem[:300]


def test_a_hand_made_manifest_and_subject_folder_are_read(tmp_path):
    root = _dataset(tmp_path / "data", _doc([{"seed": 7, "path": "subject_7"}]))  # seconds and bytes optional
    assert TrainingData(root, 24, 24, 1).subjects == ["subject_7"]
    assert split_subjects(root, 0) == (["subject_7"], [])
    seeded = _subject(tmp_path / "one", lambda doc: doc["dla"].update(synth={"seed": 3}))
    assert TrainingData(seeded, 24, 24, 1).subjects == ["one"]
    odd = _subject(tmp_path / "odd", lambda doc: doc["dla"].update(synth={"seed": True}))  # not a seed: unseeded
    assert split_subjects(odd, 0) == (["odd"], [])


@pytest.mark.parametrize(
    "change, needle",
    [
        (lambda doc: [doc], "expected a JSON object, found list"),
        (lambda doc: doc.update(dla=["synth"]), "'dla' must be an object"),
        (lambda doc: doc["dla"].update(synth=[{"seed": 3}]), "'dla.synth' must be an object, found list"),
        (lambda doc: doc["dla"].update(synth="x" * 100_000), "'dla.synth' must be an object, found str"),
    ],
)
def test_bad_subject_transforms_are_one_line_errors(tmp_path, change, needle):
    """A subject folder (the training root, or a subject a resumed `dla synth` finds) whose
    transforms.json is not an object, or whose "dla" or "dla.synth" is not one."""
    from dlacli.data.dataset import synth_record

    folder = _subject(tmp_path / "subject_7", change)
    for read in (lambda: TrainingData(folder, 24, 24, 1), lambda: synth_record(folder)):
        with pytest.raises(DlaInputError) as err:
            read()
        assert err.value.where == str(folder / "transforms.json") and needle in err.value.problem
        assert len(err.value.problem) < 200


def test_dla_train_refuses_a_bad_manifest_in_one_line(tmp_path, capsys):
    from dlacli.cli.app import main

    root = _dataset(tmp_path / "data", _doc([{**GOOD, "path": "../../etc"}]))
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--data", str(root), "-o", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"error: {root / 'manifest.json'}: subjects[0].path '../../etc' is not one folder name")
    assert not (tmp_path / "run").exists()


def test_other_settings_are_named_in_short_excerpts(tmp_path):
    """`dla synth --seeds` into a dataset whose manifest holds other (here hostile) settings: the
    first differences are named, each value quoted as a short excerpt."""
    from dlacli.data.dataset import DatasetSettings, synth_dataset

    settings = {"a" * 10_000: 1, "appearance": "9" * 100_000, "builtin_motions": ["\x1b[31m"] * 50_000}
    root = _dataset(tmp_path / "data", _doc([GOOD], settings=settings))
    with pytest.raises(DlaInputError) as err:
        synth_dataset([7], root, DatasetSettings(res=48))
    problem = err.value.problem
    assert err.value.where == str(root / "manifest.json") and problem.startswith("was written with other settings")
    assert "(100,000 characters) there, 'lit' now" in problem and "\x1b" not in problem and len(problem) < 400, problem


def test_resuming_remakes_entries_without_seconds_and_bytes(tmp_path):
    """A manifest entry without `seconds` and `bytes` (they are optional to read) is made again from
    its complete subject folder when `dla synth --seeds` resumes, as for a subject the manifest lacks."""
    from dlacli.data.dataset import DatasetSettings, read_manifest, synth_dataset

    settings = DatasetSettings(res=16, novel_views=0, novel_poses=0)
    root = _dataset(tmp_path / "data", _doc([{"seed": 7, "path": "subject_7"}], settings=settings.record()))
    images = root / "subject_7" / "images"
    for k in (2, 3):  # an input view folder has 4 views
        shutil.copy(images / "view_000.png", images / f"view_00{k}.png")
    manifest = synth_dataset([7], root, settings)
    assert manifest == read_manifest(root / "manifest.json")
    (entry,) = manifest["subjects"]
    assert entry["seed"] == 7 and entry["seconds"] is None and entry["bytes"] > 0


def test_a_mixed_dataset_holds_the_subjects_of_the_single_appearance_datasets(tmp_path):
    """`--appearance mixed`: each subject is, file for file, the subject a lit or an albedo dataset
    writes for its seed, and the manifest says which; over a few seeds both kinds occur."""
    from dlacli.data.dataset import DatasetSettings, subject_appearance, synth_dataset

    seeds = list(range(6))
    drawn = {s: subject_appearance(s, "mixed") for s in seeds}
    assert set(drawn.values()) == {"lit", "albedo"}
    manifest = synth_dataset(
        seeds, tmp_path / "mixed", DatasetSettings(res=16, novel_views=0, novel_poses=0, appearance="mixed")
    )
    assert manifest["settings"]["appearance"] == "mixed"
    assert {e["seed"]: e["appearance"] for e in manifest["subjects"]} == drawn
    for appearance in ("lit", "albedo"):
        chosen = [s for s in seeds if drawn[s] == appearance][:1]
        settings = DatasetSettings(res=16, novel_views=0, novel_poses=0, appearance=appearance)
        synth_dataset(chosen, tmp_path / appearance, settings)
        for seed in chosen:
            one, other = tmp_path / appearance / f"subject_{seed}", tmp_path / "mixed" / f"subject_{seed}"
            files = sorted(p.relative_to(one) for p in one.rglob("*") if p.is_file())
            assert files == sorted(p.relative_to(other) for p in other.rglob("*") if p.is_file())
            assert all((one / f).read_bytes() == (other / f).read_bytes() for f in files)


def test_an_unknown_dataset_appearance_is_one_line(tmp_path):
    from dlacli.data.dataset import DatasetSettings, synth_dataset

    with pytest.raises(DlaInputError, match="--appearance: must be one of albedo, lit, mixed"):
        synth_dataset([1], tmp_path / "d", DatasetSettings(res=16, appearance="sunny"))
    assert not (tmp_path / "d").exists()
