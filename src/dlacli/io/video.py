"""Videos through imageio-ffmpeg's bundled ffmpeg: preview videos (.mp4, H.264) written
atomically, and any video ffmpeg decodes read as a stream of frames (`open_video`), so that a
long clip never sits in memory: one decoded frame at a time. Frames come as a player shows them:
ffmpeg applies the stream's display rotation (a phone's portrait clip is usually stored sideways).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dlacli.errors import DlaInputError, one_line
from dlacli.io.atomic import atomic_path
from dlacli.limits import MAX_IMAGE_SIZE, MAX_VIDEO_FRAMES


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


# ------------------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class VideoClip:
    """A video file's frames at a chosen rate over a chosen span (`open_video`); iterate it (more
    than once if needed: each pass decodes the file again) for (index, time s, [H, W, 3] uint8)."""

    path: Path
    width: int
    height: int
    source_fps: float  # the file's frame rate, as ffmpeg reports it
    fps: float  # the rate of the frames this clip yields (<= source_fps)
    start: float  # seconds: the first yielded frame is the file's first frame at or after this
    end: float | None  # seconds: frames at or after this are not yielded (None: to the end)
    duration: float | None  # the file's duration in seconds as ffmpeg reports it (None: unknown)

    @property
    def expected_frames(self) -> int | None:
        """About how many frames the clip yields (from the reported duration; None: unknown)."""
        stop = self.end if self.end is not None else self.duration
        if stop is None or not math.isfinite(stop):
            return None
        return max(0, int(math.floor((stop - self.start) * self.fps - 1e-6)) + 1)

    def __iter__(self) -> Iterator[tuple[int, float, np.ndarray]]:
        return _frames(self)


def _rotated_size_note(record: logging.LogRecord) -> bool:
    """False for imageio-ffmpeg's warning that the frames' size differs from the stored size: what
    ffmpeg's display rotation does to a phone clip, expected here (the frames come upright)."""
    return "is different from the source frame size" not in record.getMessage()


def _ffmpeg_frames(path: Path, start: float):
    """imageio-ffmpeg's generator (the meta dict first, then raw rgb24 frames), seeking to `start`
    seconds before decoding (input-side -ss: ffmpeg decodes from the keyframe before and drops
    what precedes `start`, so the first frame is the one at `start`)."""
    import imageio_ffmpeg

    log = logging.getLogger("imageio_ffmpeg")
    if _rotated_size_note not in log.filters:
        log.addFilter(_rotated_size_note)
    params = ["-ss", f"{start:.6f}"] if start > 0 else None
    return imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24", input_params=params)


def _not_a_video(path: Path, err: BaseException | str) -> DlaInputError:
    reason = str(err).split("=== stderr ===")[0]  # imageio-ffmpeg appends ffmpeg's whole log
    return DlaInputError(path, f"ffmpeg cannot read it as a video ({one_line(reason, 100)})")


def open_video(
    path: str | os.PathLike, *, fps: float | None = None, start: float = 0.0, end: float | None = None
) -> VideoClip:
    """Open a video for streamed reading: checks that ffmpeg reads it (size, frame rate) and the
    options; DlaInputError (naming the file or the option) when not. `fps` resamples by taking,
    for output frame k, the source frame nearest to start + k / fps (None: every source frame);
    it may not exceed the file's rate. `start`/`end` in seconds from the file's start."""
    path = Path(path)
    if not path.is_file():
        raise DlaInputError(path, "no such file" if not path.exists() else "is not a file")
    if not (math.isfinite(start) and start >= 0):
        raise DlaInputError("--start", f"must be a number of seconds >= 0, got {start}")
    if end is not None and not (math.isfinite(end) and end > start):
        raise DlaInputError("--end", f"must be after --start ({start:g} s), got {end}")
    gen = _ffmpeg_frames(path, 0.0)
    try:
        meta = next(gen)
    except (OSError, RuntimeError, StopIteration, ValueError) as err:
        raise _not_a_video(path, err) from None
    finally:
        gen.close()
    size = meta.get("size") or (0, 0)
    width, height = int(size[0]), int(size[1])
    src_fps = float(meta.get("fps") or 0.0)
    if width < 1 or height < 1:
        raise DlaInputError(path, "ffmpeg found no video stream in it")
    if max(width, height) > MAX_IMAGE_SIZE:
        raise DlaInputError(path, f"frames of {width}x{height} pixels; at most {MAX_IMAGE_SIZE} a side are supported")
    if not (math.isfinite(src_fps) and src_fps > 0):
        raise DlaInputError(path, "ffmpeg reports no frame rate for its video stream")
    out_fps = src_fps
    if fps is not None:
        if not (math.isfinite(fps) and fps > 0):
            raise DlaInputError("--fps", f"must be > 0, got {fps}")
        if fps > src_fps * (1 + 1e-6):
            raise DlaInputError("--fps", f"{fps:g} is above the video's own rate ({src_fps:g} fps)")
        out_fps = float(fps)
    duration = meta.get("duration")
    duration = float(duration) if duration is not None and math.isfinite(float(duration)) else None
    if duration is not None and duration <= 0:  # a still image (ffmpeg reads it as one frame): unknown
        duration = None
    if duration is not None and start >= duration:
        raise DlaInputError("--start", f"{start:g} s is at or after the video's end ({duration:g} s)")
    clip = VideoClip(path, width, height, src_fps, out_fps, float(start), end, duration)
    n = clip.expected_frames
    if n is not None and n > MAX_VIDEO_FRAMES:
        raise DlaInputError(
            path, f"{n:,} frames at {out_fps:g} fps; at most {MAX_VIDEO_FRAMES:,} are supported (use --start/--end)"
        )
    return clip


def _frames(clip: VideoClip) -> Iterator[tuple[int, float, np.ndarray]]:
    """Decode the clip's source frames one at a time; yield those the rate and span select."""
    w, h = clip.width, clip.height
    gen = _ffmpeg_frames(clip.path, clip.start)
    ratio = clip.source_fps / clip.fps  # source frames per output frame (>= 1)
    k = 0  # the next output frame
    try:
        meta = next(gen)
        if tuple(meta.get("size") or ()) != (w, h):
            raise DlaInputError(clip.path, "the video's frame size changed while reading it")
        for i, raw in enumerate(gen):
            t = clip.start + i / clip.source_fps
            if clip.end is not None and t >= clip.end - 1e-9:
                break
            if len(raw) != w * h * 3:
                raise DlaInputError(clip.path, f"a decoded frame holds {len(raw):,} bytes, expected {w * h * 3:,}")
            # output frame k takes source frame round(k * ratio): yield this one for every k that does
            while int(math.floor(k * ratio + 0.5)) == i:
                if k >= MAX_VIDEO_FRAMES:
                    raise DlaInputError(
                        clip.path, f"more than {MAX_VIDEO_FRAMES:,} frames; use --start/--end or a lower --fps"
                    )
                yield k, clip.start + k / clip.fps, np.frombuffer(raw, np.uint8).reshape(h, w, 3)
                k += 1
    except (OSError, RuntimeError) as err:
        raise _not_a_video(clip.path, err) from None
    finally:
        gen.close()
