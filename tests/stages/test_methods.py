"""The lift-method registry (dlacli.stages.methods): one spec syntax, one name per method."""

from __future__ import annotations

import re

import pytest

from dlacli.errors import DlaInputError
from dlacli.stages import methods


def test_specs_name_the_registry_and_refuse_in_one_line():
    spec = methods.parse_method("unproject:steps=20,render_size=256,view_colour=false")
    assert spec.name == "unproject" and spec.options() == {"steps": 20, "render_size": 256, "view_colour": False}
    assert spec.given == {"steps", "render_size", "view_colour"}
    assert methods.parse_method("unproject").options() == {"steps": 0}  # the bare name: the mesh unprojection
    assert spec.with_options(resolution=64).options() == {**spec.options(), "resolution": 64}
    for text, needle in (
        ("magic", "unknown method 'magic' (one of: learned, unproject)"),
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
    from dlacli.io.views import read_views
    from dlacli.stages.synth import synth

    views = read_views(synth(8105, tmp_path / "s", res=32, novel_views=0, novel_poses=0))
    avatar = methods.make_spec("unproject", resolution=32, gaussians=512).lift(views).avatar
    assert avatar.encoder == "unproject" and avatar.extra["lift"]["steps"] == 0
