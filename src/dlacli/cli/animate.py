"""`dla animate`: avatar + motion -> USD animation (+ preview video)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def animate(
    avatar: Path = typer.Argument(..., metavar="AVATAR", help="avatar.npz"),
    motion: str = typer.Argument(..., metavar="MOTION", help="Native motion.npz, BVH, ASF/AMC (.amc with its .asf beside it, or CLIP.amc:SKELETON.asf), AMASS .npz, or a built-in name: idle, walk, turnaround, wave."),
    output: Path = typer.Option(..., "--output", "-o", help="USD file: .usdc (binary, default), .usda (text) or .usd."),
    preview: Optional[Path] = typer.Option(None, "--preview", help="Also write a preview .mp4 splatted from a camera that follows the body."),
    schema: str = typer.Option("instancer", "--schema", help="instancer (UsdGeom.PointInstancer), particlefield (UsdVol.ParticleField3DGaussianSplat) or both."),
    gaussians: int = typer.Option(131_072, "--gaussians", min=2, help="Gaussians per frame: half sampled uniformly in UV, half on the surface."),
    fps: Optional[float] = typer.Option(None, "--fps", help="Resample the motion to this frame rate (default: the motion's own)."),
    preview_size: int = typer.Option(512, "--preview-size", min=16, help="Preview video size in pixels (square)."),
) -> None:
    """Animate an avatar with a motion and write it as USD (and a preview video)."""
    from dlacli.body.motion_source import load_motion
    from dlacli.cli.progress import progress_bar
    from dlacli.errors import DlaInputError
    from dlacli.io.avatar import read_avatar
    from dlacli.io.usd import SCHEMAS, SUFFIXES
    from dlacli.io.video import write_video
    from dlacli.stages.animate import pose_avatar, preview_frames, write_animation

    if schema not in SCHEMAS:
        raise DlaInputError("--schema", f"unknown schema {schema!r} (use one of {', '.join(SCHEMAS)})")
    if output.suffix.lower() not in SUFFIXES:
        raise DlaInputError(output, "the animation is a .usdc, .usda or .usd file")
    if preview is not None and preview.suffix.lower() != ".mp4":
        raise DlaInputError(preview, "the preview is an .mp4 file")
    if fps is not None and not fps > 0:
        raise DlaInputError("--fps", f"must be > 0, got {fps}")
    av = read_avatar(avatar)
    mot = load_motion(motion, fps=fps, phenotype=av.body.phenotype)
    with progress_bar("posing", mot.num_frames) as update:
        anim = pose_avatar(av, mot, gaussians, where=str(avatar), progress=update)
    if preview is not None:
        with progress_bar("preview", anim.num_frames) as update:
            def frames():
                for t, frame in enumerate(preview_frames(anim, preview_size)):
                    update(t + 1)
                    yield frame
            write_video(frames(), preview, anim.fps)
    write_animation(anim, output, schema)
    typer.echo(str(output))


def register(app: typer.Typer) -> None:
    app.command("animate")(animate)
