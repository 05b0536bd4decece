"""`dla animate`: avatar + motion -> USD animation (+ preview video)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli.options import auto_note, finite, gaussian_count, naming

# pose_avatar holds positions, rotations and scales of every frame (40 bytes a Gaussian-frame):
# 2^27 of them is ~5 GB, e.g. 131,072 Gaussians x 1,024 frames.
MAX_GAUSSIAN_FRAMES = 1 << 27


def animate(
    avatar: Path = typer.Argument(..., metavar="AVATAR", help="avatar.npz"),
    motion: str = typer.Argument(..., metavar="MOTION", help="Native motion.npz, BVH, ASF/AMC (.amc with its .asf beside it, or CLIP.amc:SKELETON.asf), AMASS .npz, or a built-in name: idle, walk, turnaround, wave."),
    output: Path = typer.Option(..., "--output", "-o", help="USD file: .usdc (binary, default), .usda (text) or .usd."),
    preview: Optional[Path] = typer.Option(None, "--preview", help="Also write a preview .mp4 splatted from a camera that follows the body."),
    schema: str = typer.Option("points", "--schema", help="points (UsdGeom.Points: coloured in Blender), instancer (UsdGeom.PointInstancer: oriented, anisotropic), particlefield (UsdVol.ParticleField3DGaussianSplat, for splat renderers) or both (points + particlefield)."),
    tolerance: float = typer.Option(1.0, "--tolerance", min=0.0, max=100.0, callback=finite, metavar="MM", help="Compact the time samples: leave out what USD's interpolation reproduces within this many millimetres (orientations and sizes: formats/usd.md); 0 writes every frame exactly."),
    gaussians: Optional[str] = typer.Option(None, "--gaussians", callback=gaussian_count, metavar="N|auto", help="Gaussians per frame, half sampled uniformly in UV, half on the surface (default: the count the avatar was lifted with, else 131,072); 'auto': the count lift --gaussians auto recorded, scaled to the person's size in --preview-size turntable cameras, else the fewest whose sampling noise costs under 0.2 dB (docs/benchmarks.md, 'The Gaussian budget')."),
    checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="The learned decoder's checkpoint folder, when it is not in the checkpoints cache (~/.cache/dla/checkpoints) under the hash the avatar records."),
    seed: Optional[int] = typer.Option(None, "--seed", min=0, max=2**32 - 1, help="Seed of the sample points (default: the avatar's own)."),
    fps: Optional[float] = typer.Option(None, "--fps", min=0.1, max=1000.0, callback=finite, help="Resample the motion to this frame rate (default: the motion's own)."),
    preview_size: int = typer.Option(512, "--preview-size", min=16, max=4096, help="Preview video size in pixels (square)."),
    allow_missing_joints: bool = typer.Option(False, "--allow-missing-joints", help="Accept a motion file lacking joints its skeleton family always has (e.g. a renamed LeftUpLeg): those anny bones stay at rest."),
) -> None:
    """Animate an avatar with a motion and write it as USD (and a preview video)."""
    from dlacli.stages.motion_source import load_motion, split_spec
    from dlacli.cli.progress import progress_bar
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import check_outputs, output_group
    from dlacli.io.avatar import read_avatar
    from dlacli.io.usd import SCHEMAS, SUFFIXES
    from dlacli.io.video import write_video
    from dlacli.stages.render import sample_settings
    from dlacli.stages.animate import animation_preview_frames, pose_avatar, write_animation

    if schema not in SCHEMAS:
        raise DlaInputError("--schema", f"unknown schema {schema!r} (use one of {', '.join(SCHEMAS)})")
    if output.suffix.lower() not in SUFFIXES:
        raise DlaInputError(output, "the animation is a .usdc, .usda or .usd file")
    if preview is not None and preview.suffix.lower() != ".mp4":
        raise DlaInputError(preview, "the preview is an .mp4 file")
    check_outputs(files=[output, preview], inputs=[avatar, checkpoint, *split_spec(motion)])
    av = read_avatar(avatar)
    mot = load_motion(motion, fps=fps, phenotype=av.body.phenotype, allow_missing_joints=allow_missing_joints)
    if gaussians == "auto":
        from dlacli.stages.budget import AUTO_VIEWS, auto_gaussians
        from dlacli.stages.render import turntable_cameras

        with naming(avatar=avatar, pose=avatar, phenotype=avatar):
            choice = auto_gaussians(av, turntable_cameras(av, AUTO_VIEWS, preview_size), seed=seed,
                                    checkpoint=None if checkpoint is None else str(checkpoint))  # fmt: skip
        gaussians = choice.count
        typer.echo(auto_note(choice), err=True)
    with naming(avatar=avatar):
        gaussians, seed = sample_settings(av, gaussians, seed)
    if mot.num_frames * gaussians > MAX_GAUSSIAN_FRAMES:
        raise DlaInputError("--gaussians", f"{mot.num_frames} frames x {gaussians} Gaussians is more than dla animates at once "
                                           f"({MAX_GAUSSIAN_FRAMES:.3g} Gaussian-frames): lower --fps or --gaussians, or cut the motion")  # fmt: skip
    with naming(avatar=avatar, pose=avatar, phenotype=avatar), progress_bar("posing", mot.num_frames) as update:
        anim = pose_avatar(av, mot, gaussians, seed, where=str(avatar), progress=update,
                           checkpoint=None if checkpoint is None else str(checkpoint))
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
