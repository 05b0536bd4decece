"""`dla synth`: a synthetic subject (anny dressed in MakeHuman garments) with ground truth."""

from __future__ import annotations

from pathlib import Path

import typer


def synth(
    seed: int = typer.Option(..., "--seed", min=0, max=2**32 - 1, help="Subject seed (>= 0): the same seed gives the same files."),
    output: Path = typer.Option(..., "-o", "--output", help="Subject folder to write (replaced whole)."),
    res: int = typer.Option(512, "--res", min=16, max=4096, help="Image width and height in pixels."),
    novel_views: int = typer.Option(12, "--novel-views", min=0, max=1024, help="Ground-truth views of the input pose (0: none)."),
    novel_poses: int = typer.Option(8, "--novel-poses", min=0, max=1024, help="Ground-truth poses, 3 cameras each (0: none)."),
) -> None:
    """Write a synthetic subject: 4 input views + its true body.json, novel views and poses."""
    from dlacli.io.atomic import check_outputs
    from dlacli.stages.synth import SUBJECT_LAYOUT
    from dlacli.stages.synth import synth as run

    check_outputs(folders=[(output, SUBJECT_LAYOUT)])
    kwargs = dict(res=res, novel_views=novel_views, novel_poses=novel_poses)
    from dlacli.cli.progress import status

    with status("dla synth") as update:
        path = run(seed, output, progress=update, **kwargs)
    typer.echo(str(path))


def register(app: typer.Typer) -> None:
    app.command("synth")(synth)
