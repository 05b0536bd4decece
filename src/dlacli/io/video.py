"""Preview videos (.mp4, H.264 through imageio-ffmpeg's bundled ffmpeg), written atomically."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from dlacli.errors import DlaInputError, one_line
from dlacli.io.atomic import atomic_path


def _rgb8(frame: np.ndarray, background: float) -> np.ndarray:
    """[H, W, 3|4] float in [0, 1] or uint8 -> [H, W, 3] uint8 (RGBA composited over background)."""
    f = frame.astype(np.float32) / 255.0 if frame.dtype == np.uint8 else frame.astype(np.float32)
    if f.shape[-1] == 4:
        f = f[..., :3] * f[..., 3:] + background * (1.0 - f[..., 3:])
    return (np.clip(f, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_video(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float, background: float = 0.0) -> int:
    """Write frames ([H, W, 3] or [H, W, 4], float in [0, 1] or uint8; sizes multiple of 16 play
    everywhere) to an .mp4 at `fps`. Returns the number of frames written."""
    import imageio.v2 as imageio

    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise DlaInputError(path, "preview videos are .mp4 files")
    if not fps > 0:
        raise DlaInputError(path, f"fps must be > 0, got {fps}")
    count = 0
    with atomic_path(path) as tmp:
        try:
            writer = imageio.get_writer(
                tmp,
                format="FFMPEG",
                fps=float(fps),
                codec="libx264",
                quality=7,
                macro_block_size=16,
                ffmpeg_log_level="quiet",
            )  # failures: our one line
            try:
                for frame in frames:
                    writer.append_data(_rgb8(np.asarray(frame), background))
                    count += 1
            finally:
                writer.close()
        except (OSError, RuntimeError, BrokenPipeError) as err:  # ffmpeg missing, crashed or refused
            raise DlaInputError(path, f"ffmpeg could not write the video ({one_line(err, 160)})") from None
        if count == 0:
            raise DlaInputError(path, "no frames to write")
        if not tmp.exists() or tmp.stat().st_size == 0:
            raise DlaInputError(path, "ffmpeg wrote an empty video")
    return count
