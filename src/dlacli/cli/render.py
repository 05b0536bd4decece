"""`dla render`: RGBA images of an avatar from given cameras (and motion frames)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli.options import auto_note, finite, gaussian_count, naming

MAX_PIXELS = 1 << 30  # all images of one render together (--video keeps them in memory, 4 GiB as RGBA8)
def render(
    avatar: Path = typer.Argument(..., metavar="AVATAR", help="avatar.npz"),
    output: Path = typer.Option(..., "--output", "-o", help="Folder for f{frame:04d}_c{camera:03d}.png images."),
    cameras: Optional[Path] = typer.Option(None, "--cameras", help="transforms.json (or its folder) whose frames give the cameras; a frame's `time` picks the motion frame."),
    motion: Optional[str] = typer.Option(None, "--motion", help="Motion file or built-in name (idle, walk, turnaround, wave); default: the avatar's own pose."),
    turntable: int = typer.Option(0, "--turntable", min=0, max=3600, help="Instead of --cameras: this many cameras evenly around the body."),
    size: int = typer.Option(512, "--size", min=16, max=4096, help="Image size for --turntable."),
    video: Optional[Path] = typer.Option(None, "--video", help="Also write the images in order as an .mp4."),
    fps: float = typer.Option(24.0, "--fps", min=1.0, max=1000.0, callback=finite, help="Frame rate of --video."),
    gaussians: Optional[str] = typer.Option(None, "--gaussians", callback=gaussian_count, metavar="N|auto", help="Gaussians sampled from the avatar (default: the count it was lifted with, else 131,072); 'auto': the count lift --gaussians auto recorded, scaled to the person's size in these cameras, else the fewest whose sampling noise costs under 0.2 dB (docs/benchmarks.md, 'The Gaussian budget')."),
    checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="The learned decoder's checkpoint folder, when it is not in the checkpoints cache (~/.cache/dla/checkpoints) under the hash the avatar records."),
    seed: Optional[int] = typer.Option(None, "--seed", min=0, max=2**32 - 1, help="Seed of the sample points (default: the avatar's own)."),
    allow_missing_joints: bool = typer.Option(False, "--allow-missing-joints", help="Accept a motion file lacking joints its skeleton family always has (e.g. a renamed LeftUpLeg): those anny bones stay at rest."),
) -> None:
    """Render an avatar from the cameras of a transforms.json, or as a turntable."""
    import numpy as np
    from PIL import Image

    from dlacli.stages.motion_source import load_motion, split_spec
    from dlacli.cli.progress import progress_bar
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import atomic_dir, check_outputs, output_group
    from dlacli.io.avatar import read_avatar
    from dlacli.io.video import write_video
    from dlacli.io.views import read_transforms
    from dlacli.stages.render import render_avatar, turntable_cameras
    from dlacli.types import Cameras

    if (cameras is None) == (turntable == 0):
        raise DlaInputError("--cameras", "give either --cameras TRANSFORMS_JSON or --turntable N")
    if video is not None and video.suffix.lower() != ".mp4":
        raise DlaInputError(video, "the video is an .mp4 file")
    motion_files = split_spec(motion) if motion else ()
    check_outputs(files=[video], folders=[(output, ("f*_c*.png",))], inputs=[avatar, cameras, checkpoint, *motion_files])
    av = read_avatar(avatar)
    about_avatar = dict(avatar=avatar, pose=avatar, phenotype=avatar)  # stage errors name the file
    mot = load_motion(motion, phenotype=av.body.phenotype, allow_missing_joints=allow_missing_joints) if motion else None
    if cameras is not None:
        meta = read_transforms(cameras)
        cams = Cameras.from_c2w_opengl(meta["c2w"], meta["fx"], meta["fy"], meta["cx"], meta["cy"], meta["width"], meta["height"])
        times = meta["times"]
    else:
        with naming(**about_avatar):
            cams = turntable_cameras(av, turntable, size)
        times = [None] * turntable
    if mot is None and any(t is not None for t in times):
        raise DlaInputError("--motion", "the cameras' frames have `time` keys: pass the motion they index")
    if len(times) * cams.width * cams.height > MAX_PIXELS:
        raise DlaInputError("--cameras" if cameras is not None else "--turntable",
                            f"{len(times)} images of {cams.width}x{cams.height} are more than dla renders at once ({MAX_PIXELS / 1e9:.1f} gigapixels)")  # fmt: skip
    if gaussians == "auto":
        from dlacli.stages.budget import auto_cameras, auto_gaussians

        with naming(**about_avatar):
            choice = auto_gaussians(av, auto_cameras(cams), seed=seed, checkpoint=None if checkpoint is None else str(checkpoint))
        gaussians = choice.count
        typer.echo(auto_note(choice), err=True)
    frames = []
    with naming(**about_avatar), output_group(), atomic_dir(output) as tmp, progress_bar("rendering", len(times)) as update:
        for shot in render_avatar(av, cams, times, mot, gaussians, seed, where=str(avatar), progress=update,
                                  checkpoint=None if checkpoint is None else str(checkpoint)):
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
