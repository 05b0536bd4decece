"""Fixtures for stage tests: one small synthetic subject per session."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def subject(tmp_path_factory):
    """A 128 px synthetic subject with 4 novel views and 2 novel poses (seed 5)."""
    from dlacli.data.synth import synth

    return synth(5, tmp_path_factory.mktemp("subject") / "s5", res=128, novel_views=4, novel_poses=2)
