"""`dla view`: avatar (+ motion) -> one self-contained HTML page that splats and plays it."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli import options
from dlacli.cli.options import naming_avatar

PAGE_SUFFIXES = (".html", ".htm")


def view(
    avatar: Path = options.avatar(),
    motion: Optional[str] = options.motion(
        "The motion the page plays (default: the avatar's own pose, one frame)", short=True
    ),
    output: Optional[Path] = options.output(
        "The page, an .html file (default: AVATAR with the suffix .html).", PAGE_SUFFIXES, "web page", required=False
    ),
    gaussians: Optional[str] = options.gaussians(what="Gaussians in the page"),
    fps: Optional[float] = options.resample_fps(),
    seed: Optional[int] = options.seed(),
    checkpoint: Optional[Path] = options.checkpoint(),
    allow_missing_joints: bool = options.allow_missing_joints(),
) -> None:
    """Write a web page (WebGL2, no network) that plays the avatar: orbit, zoom, play, scrub."""
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import check_outputs
    from dlacli.io.avatar import read_avatar
    from dlacli.stages.motion.source import load_motion, split_spec
    from dlacli.stages.view import view_page, write_page

    if output is None:
        output = avatar.with_suffix(PAGE_SUFFIXES[0])
    if fps is not None and motion is None:
        raise DlaInputError("--fps", "resamples a motion: give --motion too")
    check_outputs(files=[output], inputs=[avatar, checkpoint, *(split_spec(motion) if motion else ())])
    ckpt = None if checkpoint is None else str(checkpoint)
    av = read_avatar(avatar)
    mot = None
    if motion:
        mot = load_motion(motion, fps=fps, phenotype=av.body.phenotype, allow_missing_joints=allow_missing_joints)
    with naming_avatar(avatar, motion=motion or avatar):
        html = view_page(av, mot, gaussians, seed, where=str(avatar), checkpoint=ckpt, title=avatar.stem)
    write_page(html, output)
    typer.echo(str(output))


def register(app: typer.Typer) -> None:
    app.command("view")(view)
