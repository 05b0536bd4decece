"""`dla motion convert|preview`: import third-party motions, look at any motion."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli.options import finite

motion_app = typer.Typer(
    name="motion",
    help="Motions: convert CMU BVH / ASF-AMC / AMASS to motion.npz, preview any motion as mp4.",
    no_args_is_help=True,
    add_completion=False,
)

_SPEC_HELP = (
    "A motion.npz, AMASS .npz, .bvh, .amc (its .asf beside it, or CLIP.amc:SUBJECT.asf), "
    "or a built-in name: idle, walk, turnaround, wave."
)

def convert(
    source: str = typer.Argument(..., help=_SPEC_HELP),
    output: Path = typer.Option(..., "-o", "--output", help="motion.npz to write."),
    fps: Optional[float] = typer.Option(None, "--fps", min=0.1, max=1000.0, callback=finite, help="Resample to this frame rate (default: keep the source's)."),
    asf: Optional[Path] = typer.Option(None, "--asf", help="ASF skeleton for an .amc source (default: found beside it)."),
    allow_missing_joints: bool = typer.Option(False, "--allow-missing-joints", help="Accept a motion file lacking joints its skeleton family always has (e.g. a renamed LeftUpLeg): those anny bones stay at rest."),
) -> None:
    """Retarget a motion onto anny's rig and write it as a native motion.npz."""
    from dlacli.stages.motion_source import load_motion, split_spec
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import check_outputs
    from dlacli.io.motion import write_motion

    if output.suffix.lower() != ".npz":
        raise DlaInputError(output, "the output must be a .npz file")
    check_outputs(files=[output], inputs=[*split_spec(source), asf])
    motion = load_motion(source, fps=fps, asf=asf, allow_missing_joints=allow_missing_joints)
    write_motion(motion, output)
    typer.echo(f"{output}  {motion.num_frames} frames at {motion.fps:g} fps")


def preview(
    motion_spec: str = typer.Argument(..., metavar="MOTION", help=_SPEC_HELP),
    output: Path = typer.Option(..., "-o", "--output", help="mp4 file to write."),
    fps: Optional[float] = typer.Option(None, "--fps", min=1.0, max=1000.0, callback=finite, help="Frame rate of the video (default: the motion's, at most 30)."),
    res: int = typer.Option(384, "--res", min=64, max=2048, help="Video width and height in pixels (rounded up to a multiple of 16)."),
    allow_missing_joints: bool = typer.Option(False, "--allow-missing-joints", help="Accept a motion file lacking joints its skeleton family always has (e.g. a renamed LeftUpLeg): those anny bones stay at rest."),
) -> None:
    """Render the default body doing a motion into an mp4 (left side blue, right side red)."""
    from dlacli.stages.motion_source import load_motion, split_spec
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import check_outputs
    from dlacli.io.video import write_video
    from dlacli.stages.motion_preview import motion_preview_frames

    if output.suffix.lower() != ".mp4":
        raise DlaInputError(output, "the output must be a .mp4 file")
    check_outputs(files=[output], inputs=split_spec(motion_spec))
    motion = load_motion(motion_spec, allow_missing_joints=allow_missing_joints)
    video_fps = fps if fps is not None else max(1.0, min(motion.fps, 30.0))
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
