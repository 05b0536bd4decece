"""The lift-method registry (dlacli.stages.lift.methods): one spec syntax, one name per method, and a
new method known by that name to `dla lift`, `dla bench accuracy`, `dla bench stability`, the
result rows and the report."""

from __future__ import annotations

import importlib
import json
import re
from pathlib import Path

import pytest

from dlacli.errors import DlaInputError
from dlacli.stages.lift import methods


def test_specs_name_the_registry_and_refuse_in_one_line():
    spec = methods.parse_method("unproject:steps=20,render_size=256,view_colour=false")
    assert spec.name == "unproject" and spec.options() == {"steps": 20, "render_size": 256, "view_colour": False}
    assert spec.given == {"steps", "render_size", "view_colour"}
    assert methods.parse_method("unproject").options() == {"steps": 0}  # the bare name: the mesh unprojection
    assert spec.with_options(resolution=64).options() == {**spec.options(), "resolution": 64}
    for text, needle in (
        ("magic", "unknown method 'magic' (one of: learned, residual, unproject)"),
        ("unproject:steps=x", "steps: expected an integer"),
        ("unproject:checkpoint=a", "unproject takes no 'checkpoint'"),
        ("learned", "needs checkpoint="),
        ("unproject,learned:checkpoint=c", "expected one method, got 2"),
    ):
        with pytest.raises(DlaInputError, match=re.escape(needle)) as err:
            methods.parse_method(text)
        assert err.value.where == "--method" and "\n" not in str(err.value)
    with pytest.raises(DlaInputError, match="--checkpoint"):
        methods.parse_method("learned", flags={"checkpoint": "--checkpoint"})


def test_the_built_in_methods_record_their_own_name(tmp_path):
    """A method's name is the encoder its avatars record (the learned one: tests/stages/test_learned.py)."""
    from dlacli.data.synth import synth
    from dlacli.io.views import read_views

    views = read_views(synth(8105, tmp_path / "s", res=32, novel_views=0, novel_poses=0))
    avatar = methods.make_spec("unproject", resolution=32, gaussians=512).lift(views).avatar
    assert avatar.encoder == "unproject" and avatar.extra["lift"]["steps"] == 0


@pytest.fixture
def toy(monkeypatch):
    """The toy method registered as a new method is: its file (tests/stages/toy_method.py,
    importable by name in the processes the benchmark starts) and one registry entry."""
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    toy_method = importlib.import_module("toy_method")
    methods.register(methods.Method(toy_method.NAME, toy_method.ToyConfig, toy_method.lift_toy, "a test's toy"))
    yield toy_method
    methods.METHODS.pop(toy_method.NAME)


def test_a_new_method_is_known_by_one_name_everywhere(toy, tmp_path, dla):
    from dlacli.bench.rows import label, read_rows
    from dlacli.data.synth import synth
    from dlacli.io.avatar import read_avatar

    views = synth(8103, tmp_path / "views", res=32, novel_views=0, novel_poses=0)
    # dla lift: the spec's options and the flags that set the toy's config fields
    code, _, err = dla("lift", views, "--method", "toy:gaussians=1024", "-o", tmp_path / "a.npz")
    assert code == 0, err
    avatar = read_avatar(tmp_path / "a.npz")
    assert avatar.encoder == "toy" and avatar.extra["toy"] == {"gaussians": 1024}
    code, _, err = dla("lift", views, "--method", "toy", "--gaussians", "512", "-o", tmp_path / "b.npz")
    assert code == 0 and read_avatar(tmp_path / "b.npz").extra["toy"] == {"gaussians": 512}, err
    code, _, err = dla("lift", views, "--method", "toy", "--resolution", "64", "-o", tmp_path / "c.npz")
    assert code == 2 and "--method toy takes no resolution" in err and not (tmp_path / "c.npz").exists()
    code, _, err = dla("lift", views, "--method", "nosuch", "-o", tmp_path / "c.npz")
    assert code == 2 and "one of: learned, residual, toy, unproject" in err

    # dla bench accuracy (its lift runs in a fresh process) and stability: rows named "toy"
    rows_file = tmp_path / "rows.jsonl"
    argv = ["bench", "accuracy", "--methods", "toy:gaussians=1024", "--seeds", "8102", "--res", "32", "--json"]
    code, out, err = dla(*argv, "--jsonl", rows_file)
    assert code == 0, err
    printed = [json.loads(line) for line in out.splitlines()]
    assert len(printed) == 3 and {r["method"] for r in printed} == {"toy"}
    assert all(r["config"]["gaussians"] == 1024 and r["metrics"]["iou"] > 0.3 for r in printed)
    argv = ["bench", "stability", "--methods", "toy,unproject", "--seeds", "8104", "--res", "32"]
    argv += ["--perturbations", "fewer_views", "--levels", "2", "--jsonl", rows_file]
    code, _, err = dla(*argv)
    assert code == 0, err
    rows = read_rows(rows_file)
    assert [r["method"] for r in rows].count("toy") == 3 + 4 and all(r.get("status", "ok") == "ok" for r in rows)
    assert {label(r) for r in rows} == {"toy gaussians=1024", "toy gaussians=2048", "unproject steps=0"}

    # the report's tables and failures know it by the same name
    code, _, err = dla("bench", "report", rows_file, "-o", tmp_path / "page.md")
    assert code == 0, err
    page = (tmp_path / "page.md").read_text()
    assert "| **toy gaussians=1024** | 1 |" in page or "| toy gaussians=1024 | 1 |" in page
    assert "| toy gaussians=2048 |" in page and "| unproject steps=0 |" in page
