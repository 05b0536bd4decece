"""`dla render`: RGBA images of an avatar from given cameras (and motion frames)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli import options
from dlacli.cli.options import auto_note, naming_avatar
from dlacli.limits import MAX_RENDER_PIXELS


def render(
    avatar: Path = options.avatar(),
    output: Path = options.output("Folder for f{frame:04d}_c{camera:03d}.png images."),
    cameras: Optional[Path] = typer.Option(
        None,
        "--cameras",
        help="transforms.json (or its folder) whose frames give the cameras; a frame's `time` picks the motion frame.",
    ),
    motion: Optional[str] = options.motion("The motion to pose the avatar with (default: the avatar's own pose)"),
    turntable: int = typer.Option(
        0, "--turntable", min=0, max=3600, help="Instead of --cameras: this many cameras evenly around the body."
    ),
    size: int = options.image_size(512, "Image size for --turntable."),
    video: Optional[Path] = options.side_output(
        "--video", "Also write the images in order as an .mp4.", (".mp4",), "video"
    ),
    fps: float = options.video_fps(24.0, "Frame rate of --video."),
    gaussians: Optional[str] = options.gaussians(auto_cameras="these cameras"),
    checkpoint: Optional[Path] = options.checkpoint(),
    seed: Optional[int] = options.seed(),
    allow_missing_joints: bool = options.allow_missing_joints(),
) -> None:
    """Render an avatar from the cameras of a transforms.json, or as a turntable."""
    import numpy as np
    from PIL import Image

    from dlacli.cli.progress import progress_bar
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import atomic_dir, check_outputs, output_group
    from dlacli.io.avatar import read_avatar
    from dlacli.io.video import write_video
    from dlacli.io.views import read_transforms
    from dlacli.stages.motion.source import load_motion, split_spec
    from dlacli.stages.render import render_avatar, turntable_cameras
    from dlacli.types import Cameras

    if (cameras is None) == (turntable == 0):
        raise DlaInputError("--cameras", "give either --cameras TRANSFORMS_JSON or --turntable N")
    motion_files = split_spec(motion) if motion else ()
    inputs = [avatar, cameras, checkpoint, *motion_files]
    check_outputs(files=[video], folders=[(output, ("f*_c*.png",))], inputs=inputs)
    ckpt = None if checkpoint is None else str(checkpoint)
    av = read_avatar(avatar)
    mot = None
    if motion:
        mot = load_motion(motion, phenotype=av.body.phenotype, allow_missing_joints=allow_missing_joints)
    if cameras is not None:
        meta = read_transforms(cameras)
        cams = Cameras.from_c2w_opengl(
            meta["c2w"], meta["fx"], meta["fy"], meta["cx"], meta["cy"], meta["width"], meta["height"]
        )
        times = meta["times"]
    else:
        with naming_avatar(avatar):
            cams = turntable_cameras(av, turntable, size)
        times = [None] * turntable
    if mot is None and any(t is not None for t in times):
        raise DlaInputError("--motion", "the cameras' frames have `time` keys: pass the motion they index")
    if len(times) * cams.width * cams.height > MAX_RENDER_PIXELS:
        raise DlaInputError(
            "--cameras" if cameras is not None else "--turntable",
            f"{len(times)} images of {cams.width}x{cams.height} are more than dla renders at once "
            f"({MAX_RENDER_PIXELS / 1e9:.1f} gigapixels)",
        )
    if gaussians == "auto":
        from dlacli.stages.budget import auto_cameras, auto_gaussians

        with naming_avatar(avatar):
            choice = auto_gaussians(av, auto_cameras(cams), seed=seed, checkpoint=ckpt)
        gaussians = choice.count
        typer.echo(auto_note(choice), err=True)
    elif gaussians is None:
        from dlacli.stages.budget import auto_cameras, budget_default

        with naming_avatar(avatar):
            choice = budget_default(av, auto_cameras(cams))
        if choice is not None:
            gaussians = choice.count
            typer.echo(auto_note(choice, default=True), err=True)
    frames = []
    with (
        naming_avatar(avatar),
        output_group(),
        atomic_dir(output) as tmp,
        progress_bar("rendering", len(times)) as update,
    ):
        for shot in render_avatar(
            av, cams, times, mot, gaussians, seed, where=str(avatar), progress=update, checkpoint=ckpt
        ):
            rgba8 = (np.clip(shot.rgba, 0, 1) * 255 + 0.5).astype(np.uint8)
            Image.fromarray(rgba8, "RGBA").save(tmp / shot.name)
            if video is not None:
                frames.append((shot.frame, shot.camera, rgba8))
        if video is not None:
            frames.sort(key=lambda s: (s[0], s[1]))
            write_video((s[2] for s in frames), video, fps)
    typer.echo(str(output))


def register(app: typer.Typer) -> None:
    app.command("render")(render)
