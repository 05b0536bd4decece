"""The dream-backend registry (dlacli.stages.dream.backends): a new backend as it lands is its
views function (this file's toy) plus one `register(Backend(...))` line, and it is known by that
name to `dla dream`, `dla bench accuracy --input photo` and the result rows."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dlacli.paths import sample_keypoints, sample_photo
from dlacli.stages.dream import backends


def toy_views(rgb, alpha, cam, vertices, loaded, *, frames, steps, seed, say, prior=None):
    """The shell backend's views, darkened to half: a backend of its own, told apart by its pixels."""
    from dlacli.stages.dream.shell import template_views

    images, masks, cams = template_views(rgb, alpha, cam, vertices)
    images[1:] *= 0.5
    return images, masks, cams, {"toy": {"gain": 0.5}}


@pytest.fixture
def toy():
    backends.register(backends.Backend("toy", "a test's toy", toy_views))
    yield
    backends.BACKENDS.pop("toy")


def test_a_new_backend_is_known_by_one_name_everywhere(toy, tmp_path, dla):
    from dlacli.bench.rows import label, read_rows
    from dlacli.io.views import read_views

    photo = ["dream", sample_photo(), "--keypoints", sample_keypoints(), "--res", "64", "--fit-steps", "3"]
    code, _, err = dla(*photo, "--backend", "toy", "-o", tmp_path / "toy")
    assert code == 0, err
    code, _, err = dla(*photo, "--backend", "shell", "-o", tmp_path / "shell")
    assert code == 0, err
    toy_set, shell_set = read_views(tmp_path / "toy"), read_views(tmp_path / "shell")
    info = json.loads((tmp_path / "toy" / "transforms.json").read_text())["dla"]["dream"]
    assert info["backend"] == "toy" and info["toy"] == {"gain": 0.5}
    np.testing.assert_array_equal(toy_set.images[0], shell_set.images[0])  # view 0: the framed photo
    np.testing.assert_allclose(toy_set.images[1:], shell_set.images[1:] * 0.5, atol=1.0 / 255)  # 8-bit PNGs

    code, _, err = dla(*photo, "--backend", "toy", "--prior", "shipped", "-o", tmp_path / "p")
    assert code == 2 and err.strip() == "error: --prior: applies to --backend body only"
    code, _, err = dla(*photo, "--backend", "nosuch", "-o", tmp_path / "n")
    assert code == 2 and "one of: body, shell, template, diffusion, toy" in err and not (tmp_path / "n").exists()

    rows_file = tmp_path / "rows.jsonl"
    argv = ["bench", "accuracy", "--input", "photo", "--backend", "toy", "--methods", "unproject", "--seeds", "8106"]
    code, _, err = dla(*argv, "--res", "64", "--fit-steps", "3", "--jsonl", rows_file)
    assert code == 0, err
    rows = read_rows(rows_file)
    assert rows and {r["config"]["backend"] for r in rows} == {"toy"}
    assert all(label(r).startswith("photo/toy unproject") for r in rows)
