"""Fixtures for the training tests: one small synthetic dataset per session."""

from __future__ import annotations

import pytest

RES = 48
NOVEL_VIEWS, NOVEL_POSES = 2, 2


@pytest.fixture(scope="session")
def dataset(tmp_path_factory):
    """A dataset folder of 2 lit, full-wardrobe subjects (seeds 21, 22) at 48 px with 2 novel
    views and 2 novel poses x 3 cameras each (built-in motions for the target poses)."""
    from dlacli.data.dataset import DatasetSettings, synth_dataset

    root = tmp_path_factory.mktemp("dataset") / "data"
    settings = DatasetSettings(res=RES, novel_views=NOVEL_VIEWS, novel_poses=NOVEL_POSES)
    synth_dataset([22, 21], root, settings, jobs=1)
    return root
