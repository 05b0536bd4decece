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
    help="Motions: convert CMU BVH / ASF-AMC / AMASS to motion.npz, fit one to a video, preview any motion as mp4.",
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
    from dlacli.stages.motion.source import load_motion, split_spec

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
    from dlacli.stages.motion.preview import motion_preview_frames
    from dlacli.stages.motion.source import load_motion, split_spec

    check_outputs(files=[output], inputs=split_spec(motion_spec))
    motion = load_motion(motion_spec, allow_missing_joints=allow_missing_joints)
    video_fps = fps if fps is not None else max(MIN_VIDEO_FPS, min(motion.fps, PREVIEW_MAX_FPS))
    if abs(video_fps - motion.fps) > 1e-9:
        from dlacli.body.retarget import resample_motion

        motion = resample_motion(motion, video_fps)
    res = -(-res // 16) * 16
    write_video(motion_preview_frames(motion, res), output, video_fps)
    typer.echo(f"{output}  {motion.num_frames} frames at {video_fps:g} fps, {res}x{res}")


def from_video(
    video: Path = typer.Argument(..., metavar="VIDEO", help="A video of one person (any file ffmpeg reads)."),
    output: Path = options.output("motion.npz to write.", (".npz",), "motion"),
    fps: Optional[float] = options.resample_fps("Frame rate of the motion (default: the video's; at most it)."),
    start: float = typer.Option(
        0.0, "--start", min=0.0, callback=options.finite, help="Start, seconds into the video."
    ),
    end: Optional[float] = typer.Option(
        None, "--end", min=0.0, callback=options.finite, help="End, seconds into the video (default: its end)."
    ),
    preview: Optional[Path] = options.side_output(
        "--preview", "Also write an mp4 of the fitted body drawn over the clip.", (".mp4",), "video"
    ),
    lifter: Optional[Path] = typer.Option(
        None,
        "--lifter",
        help="Pose-lifter weights (RUN/lifter.safetensors of `dla train --method lifter`; default: the shipped ones).",
    ),
    landmarks: str = options.landmarks(),
) -> None:
    """Fit anny's motion to a video of a person (MediaPipe Pose per frame, one temporal fit)."""
    from dlacli.cli.progress import progress_bar
    from dlacli.io.atomic import check_outputs, output_group
    from dlacli.io.detect import landmark_model
    from dlacli.io.motion import write_motion
    from dlacli.io.video import open_video, write_video
    from dlacli.nn.lifter import load_lifter
    from dlacli.stages.motion.video import preview_frames, video_to_motion

    check_outputs(files=[output, preview], inputs=[video, lifter])
    landmark_model(landmarks)  # a model not installed fails before any work
    lifter_model = load_lifter(lifter)
    clip = open_video(video, fps=fps, start=start, end=end)
    with progress_bar("from-video", clip.expected_frames) as update:
        result = video_to_motion(
            clip,
            detect_progress=lambda done, total: update(done, total, "detecting"),
            fit_progress=lambda done, total: update(done, total, "fitting"),
            lifter=lifter_model,
            landmarks=landmarks,
        )
    motion = result.motion
    with output_group():  # the motion and its preview land together or not at all
        write_motion(motion, output)
        if preview is not None:
            with progress_bar("preview", motion.num_frames) as update:
                frames = preview_frames(clip, result)
                write_video((update(k + 1) or f for k, f in enumerate(frames)), preview, motion.fps)
    if result.missing:
        spans = ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in result.missing[:10])
        more = f" and {len(result.missing) - 10} more ranges" if len(result.missing) > 10 else ""
        count = sum(b - a + 1 for a, b in result.missing)
        other = len(result.detections.switched)
        note = f", {other} of them showing another person than the tracked one" if other else ""
        typer.echo(
            f"warning: no person in {count} of {motion.num_frames} frames ({spans}{more}{note}): interpolated", err=True
        )
    det, sec = result.detections, result.seconds
    if det.unswapped:
        typer.echo(
            f"note: left and right swapped back in {len(det.unswapped)} frames "
            f"(the detector's labels changed sides at once, from frame {det.unswapped[0]})",
            err=True,
        )
    typer.echo(
        f"{output}  {motion.num_frames} frames at {motion.fps:g} fps from {det.width}x{det.height} video"
        f"  (detect {sec['detect']:.1f} s with the {landmarks} landmarks, fit {sec['fit']:.1f} s)"
    )


motion_app.command("convert")(convert)
motion_app.command("from-video")(from_video)
motion_app.command("preview")(preview)


def register(app: typer.Typer) -> None:
    app.add_typer(motion_app, name="motion")
