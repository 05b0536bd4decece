"""`dla render`: RGBA images of an avatar from given cameras (and motion frames)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def render(
    avatar: Path = typer.Argument(..., metavar="AVATAR", help="avatar.npz"),
    output: Path = typer.Option(..., "--output", "-o", help="Folder for f{frame:04d}_c{camera:03d}.png images."),
    cameras: Optional[Path] = typer.Option(None, "--cameras", help="transforms.json (or its folder) whose frames give the cameras; a frame's `time` picks the motion frame."),
    motion: Optional[str] = typer.Option(None, "--motion", help="Motion file or built-in name (idle, walk, turnaround, wave); default: the avatar's own pose."),
    turntable: int = typer.Option(0, "--turntable", min=0, help="Instead of --cameras: this many cameras evenly around the body."),
    size: int = typer.Option(512, "--size", min=1, help="Image size for --turntable."),
    video: Optional[Path] = typer.Option(None, "--video", help="Also write the images in order as an .mp4."),
    fps: float = typer.Option(24.0, "--fps", help="Frame rate of --video."),
    gaussians: int = typer.Option(131_072, "--gaussians", min=2, help="Gaussians sampled from the avatar."),
) -> None:
    """Render an avatar from the cameras of a transforms.json, or as a turntable."""
    import numpy as np
    from PIL import Image

    from dlacli.body.motion_source import load_motion
    from dlacli.cli.progress import progress_bar
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import atomic_dir
    from dlacli.io.avatar import read_avatar
    from dlacli.io.video import write_video
    from dlacli.io.views import read_transforms
    from dlacli.stages.render import render_avatar, turntable_cameras
    from dlacli.types import Cameras

    if (cameras is None) == (turntable == 0):
        raise DlaInputError("--cameras", "give either --cameras TRANSFORMS_JSON or --turntable N")
    av = read_avatar(avatar)
    mot = load_motion(motion, phenotype=av.body.phenotype) if motion else None
    if cameras is not None:
        meta = read_transforms(cameras)
        cams = Cameras.from_c2w_opengl(meta["c2w"], meta["fx"], meta["fy"], meta["cx"], meta["cy"], meta["width"], meta["height"])
        times = meta["times"]
    else:
        cams = turntable_cameras(av, turntable, size)
        times = [None] * turntable
    if mot is None and any(t is not None for t in times):
        raise DlaInputError("--motion", "the cameras' frames have `time` keys: pass the motion they index")
    frames = []
    with atomic_dir(output) as tmp, progress_bar("rendering", len(times)) as update:
        for shot in render_avatar(av, cams, times, mot, gaussians, where=str(avatar), progress=update):
            Image.fromarray((np.clip(shot.rgba, 0, 1) * 255 + 0.5).astype(np.uint8), "RGBA").save(tmp / shot.name)
            if video is not None:
                frames.append(shot)
        if video is not None:
            frames.sort(key=lambda s: (s.frame, s.camera))
            write_video((s.rgba for s in frames), video, fps)
    typer.echo(str(output))





def register(app: typer.Typer) -> None:
    app.command("render")(render)
