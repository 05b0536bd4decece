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
