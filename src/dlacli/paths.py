"""Where dla keeps caches: one folder that survives between runs.

`DLA_CACHE_DIR` overrides the default `~/.cache/dla`. anny's model cache lives in its `anny/`
subfolder (set through `ANNY_CACHE_DIR` before anny is imported, unless the user set it).
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir(sub: str = "") -> Path:
    root = Path(os.environ.get("DLA_CACHE_DIR") or Path.home() / ".cache" / "dla")
    path = root / sub if sub else root
    path.mkdir(parents=True, exist_ok=True)
    return path


def checkpoints_dir() -> Path:
    """Where installed network checkpoints live, one folder per content hash (formats/checkpoint.md)."""
    return cache_dir("checkpoints")


def sample_photo() -> Path:
    """The photo `dla dream` and the demo start from (assets/sample_photo.png, licence in assets/LICENSES.md)."""
    return Path(__file__).resolve().parent / "assets" / "sample_photo.png"


def sample_keypoints() -> Path:
    """The sample photo's COCO-17 keypoints (`dla dream --keypoints`; also its 3D landmarks)."""
    return sample_photo().with_name("sample_photo_keypoints.json")
