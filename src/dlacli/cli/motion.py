"""`dla motion convert|preview`: import third-party motions, look at any motion."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli import options
from dlacli.limits import MIN_VIDEO_FPS

PREVIEW_MAX_FPS = 30.0  # a preview plays the motion at its own rate up to this

motion_app = typer.Typer(
    name="motion",
    help="Motions: convert CMU BVH / ASF-AMC / AMASS to motion.npz, preview any motion as mp4.",
    no_args_is_help=True,
    add_completion=False,
)


def convert(
    source: str = options.motion_argument(metavar="SOURCE"),
    output: Path = options.output("motion.npz to write.", (".npz",), "motion"),
    fps: Optional[float] = options.resample_fps("Resample to this frame rate (default: keep the source's)."),
    asf: Optional[Path] = typer.Option(
        None, "--asf", help="ASF skeleton for an .amc source (default: found beside it)."
    ),
    allow_missing_joints: bool = options.allow_missing_joints(),
) -> None:
    """Retarget a motion onto anny's rig and write it as a native motion.npz."""
    from dlacli.io.atomic import check_outputs
    from dlacli.io.motion import write_motion
    from dlacli.stages.motion_source import load_motion, split_spec

    check_outputs(files=[output], inputs=[*split_spec(source), asf])
    motion = load_motion(source, fps=fps, asf=asf, allow_missing_joints=allow_missing_joints)
    write_motion(motion, output)
    typer.echo(f"{output}  {motion.num_frames} frames at {motion.fps:g} fps")


def preview(
    motion_spec: str = options.motion_argument(),
    output: Path = options.output("mp4 file to write.", (".mp4",), "video"),
    fps: Optional[float] = options.video_fps(None, "Frame rate of the video (default: the motion's, at most 30)."),
    res: int = options.image_size(
        384, "Video width and height in pixels (rounded up to a multiple of 16).", "--res", minimum=64, maximum=2048
    ),
    allow_missing_joints: bool = options.allow_missing_joints(),
) -> None:
    """Render the default body doing a motion into an mp4 (left side blue, right side red)."""
    from dlacli.io.atomic import check_outputs
    from dlacli.io.video import write_video
    from dlacli.stages.motion_preview import motion_preview_frames
    from dlacli.stages.motion_source import load_motion, split_spec

    check_outputs(files=[output], inputs=split_spec(motion_spec))
    motion = load_motion(motion_spec, allow_missing_joints=allow_missing_joints)
    video_fps = fps if fps is not None else max(MIN_VIDEO_FPS, min(motion.fps, PREVIEW_MAX_FPS))
    if abs(video_fps - motion.fps) > 1e-9:
        from dlacli.body.retarget import resample_motion

        motion = resample_motion(motion, video_fps)
    res = -(-res // 16) * 16
    write_video(motion_preview_frames(motion, res), output, video_fps)
    typer.echo(f"{output}  {motion.num_frames} frames at {video_fps:g} fps, {res}x{res}")


motion_app.command("convert")(convert)
motion_app.command("preview")(preview)


def register(app: typer.Typer) -> None:
    app.add_typer(motion_app, name="motion")
