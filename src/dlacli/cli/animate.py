"""`dla animate`: avatar + motion -> USD animation (+ preview video)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli import options
from dlacli.cli.options import auto_note, naming_avatar
from dlacli.limits import USD_SUFFIXES


def animate(
    avatar: Path = options.avatar(),
    motion: str = options.motion_argument(),
    output: Path = options.output(
        "USD file: .usdc (binary, default), .usda (text) or .usd.", USD_SUFFIXES, "animation"
    ),
    preview: Optional[Path] = options.side_output(
        "--preview", "Also write a preview .mp4 splatted from a camera that follows the body.", (".mp4",), "video"
    ),
    schema: str = typer.Option(
        "points",
        "--schema",
        help="points (UsdGeom.Points: coloured in Blender), instancer (UsdGeom.PointInstancer: oriented, "
        "anisotropic), particlefield (UsdVol.ParticleField3DGaussianSplat, for splat renderers) or both "
        "(points + particlefield).",
    ),
    tolerance: float = typer.Option(
        1.0,
        "--tolerance",
        min=0.0,
        max=100.0,
        callback=options.finite,
        metavar="MM",
        help="Compact the time samples: leave out what USD's interpolation reproduces within this many "
        "millimetres (orientations and sizes: formats/usd.md); 0 writes every frame exactly.",
    ),
    gaussians: Optional[str] = options.gaussians(
        auto_cameras="--preview-size turntable cameras", what="Gaussians per frame"
    ),
    checkpoint: Optional[Path] = options.checkpoint(),
    seed: Optional[int] = options.seed(),
    fps: Optional[float] = options.resample_fps(),
    preview_size: int = options.image_size(512, "Preview video size in pixels (square).", "--preview-size"),
    allow_missing_joints: bool = options.allow_missing_joints(),
) -> None:
    """Animate an avatar with a motion and write it as USD (and a preview video)."""
    from dlacli.cli.progress import progress_bar
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import check_outputs, output_group
    from dlacli.io.avatar import read_avatar
    from dlacli.io.usd import SCHEMAS
    from dlacli.io.video import write_video
    from dlacli.stages.animate import animation_preview_frames, pose_avatar, write_animation
    from dlacli.stages.motion.source import load_motion, split_spec

    if schema not in SCHEMAS:
        raise DlaInputError("--schema", f"unknown schema {schema!r} (use one of {', '.join(SCHEMAS)})")
    check_outputs(files=[output, preview], inputs=[avatar, checkpoint, *split_spec(motion)])
    ckpt = None if checkpoint is None else str(checkpoint)
    av = read_avatar(avatar)
    mot = load_motion(motion, fps=fps, phenotype=av.body.phenotype, allow_missing_joints=allow_missing_joints)
    if gaussians is None or gaussians == "auto":  # by default the recorded budget, when there is one
        from dlacli.stages.budget import AUTO_VIEWS, auto_gaussians, budget_default
        from dlacli.stages.render import turntable_cameras

        with naming_avatar(avatar):
            cams = turntable_cameras(av, AUTO_VIEWS, preview_size)
            if gaussians is None:
                choice = budget_default(av, cams)
            else:
                choice = auto_gaussians(av, cams, seed=seed, checkpoint=ckpt)
        if choice is not None:
            typer.echo(auto_note(choice, default=gaussians is None), err=True)
            gaussians = choice.count
    with naming_avatar(avatar), progress_bar("posing", mot.num_frames) as update:
        anim = pose_avatar(av, mot, gaussians, seed, where=str(avatar), progress=update, checkpoint=ckpt)
    with output_group():  # the USD and its preview land together or not at all
        if preview is not None:
            with progress_bar("preview", anim.num_frames) as update:

                def frames():
                    for t, frame in enumerate(animation_preview_frames(anim, preview_size)):
                        update(t + 1)
                        yield frame

                write_video(frames(), preview, anim.fps)
        write_animation(anim, output, schema, tolerance / 1000.0)
    typer.echo(str(output))


def register(app: typer.Typer) -> None:
    app.command("animate")(animate)
