"""`dla view`: avatar (+ motion) -> one self-contained HTML page that splats and plays it."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli.options import finite, naming


def view(
    avatar: Path = typer.Argument(..., metavar="AVATAR", help="avatar.npz"),
    motion: Optional[str] = typer.Option(None, "--motion", "-m", help="Motion file or built-in name (idle, walk, turnaround, wave); default: the avatar's own pose, one frame."),
    output: Optional[Path] = typer.Option(None, "--output", "-o", help="The page, an .html file (default: AVATAR with the suffix .html)."),
    gaussians: Optional[int] = typer.Option(None, "--gaussians", min=2, max=4_194_304, help="Gaussians in the page, half sampled uniformly in UV, half on the surface (default: the count the avatar was lifted with, else 131,072)."),
    fps: Optional[float] = typer.Option(None, "--fps", min=0.1, max=1000.0, callback=finite, help="Resample the motion to this frame rate (default: the motion's own)."),
    seed: Optional[int] = typer.Option(None, "--seed", min=0, max=2**32 - 1, help="Seed of the sample points (default: the avatar's own)."),
    checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="The learned decoder's checkpoint folder, when it is not in the checkpoints cache (~/.cache/dla/checkpoints) under the hash the avatar records."),
    allow_missing_joints: bool = typer.Option(False, "--allow-missing-joints", help="Accept a motion file lacking joints its skeleton family always has (e.g. a renamed LeftUpLeg): those anny bones stay at rest."),
) -> None:
    """Write a web page (WebGL2, no network) that plays the avatar: orbit, zoom, play, scrub."""
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import check_outputs
    from dlacli.io.avatar import read_avatar
    from dlacli.stages.motion_source import load_motion, split_spec
    from dlacli.stages.view import view_page, write_page

    if output is None:
        output = avatar.with_suffix(".html")
    if output.suffix.lower() not in (".html", ".htm"):
        raise DlaInputError(output, "the page is an .html file")
    if fps is not None and motion is None:
        raise DlaInputError("--fps", "resamples a motion: give --motion too")
    check_outputs(files=[output], inputs=[avatar, checkpoint, *(split_spec(motion) if motion else ())])
    av = read_avatar(avatar)
    mot = load_motion(motion, fps=fps, phenotype=av.body.phenotype, allow_missing_joints=allow_missing_joints) if motion else None
    with naming(avatar=avatar, pose=avatar, phenotype=avatar, motion=motion or avatar):
        html = view_page(av, mot, gaussians, seed, where=str(avatar),
                         checkpoint=None if checkpoint is None else str(checkpoint), title=avatar.stem)  # fmt: skip
    write_page(html, output)
    typer.echo(str(output))


def register(app: typer.Typer) -> None:
    app.command("view")(view)
