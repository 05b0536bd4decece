"""`dla synth`: a synthetic subject (anny dressed in MakeHuman garments) with ground truth, or
(`--seeds`) a dataset folder of many subjects with a manifest."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli import options
from dlacli.limits import MAX_SEED, MAX_SYNTH_SEEDS


def parse_seeds(text: str) -> list[int]:
    """'A-B' (inclusive), 'S', or a comma list of both -> distinct seeds in the order given."""
    from dlacli.errors import DlaInputError

    seeds: list[int] = []
    for part in text.split(","):
        lo, sep, hi = part.strip().partition("-")
        try:
            a = int(lo)
            b = int(hi) if sep else a
        except ValueError:
            raise DlaInputError("--seeds", f"expected A-B or a comma list of seeds and ranges, got {text!r}") from None
        if a < 0 or b < a or b > MAX_SEED:
            raise DlaInputError("--seeds", f"range {part.strip()!r} must be 0 <= A <= B < 2^32")
        if len(seeds) + b - a + 1 > MAX_SYNTH_SEEDS:
            raise DlaInputError("--seeds", f"more than {MAX_SYNTH_SEEDS:,} seeds in one run")
        seeds.extend(range(a, b + 1))
    if len(set(seeds)) != len(seeds):
        raise DlaInputError("--seeds", f"lists a seed twice: {text!r}")
    return seeds


def synth(
    seed: Optional[int] = options.seed("One subject: its seed (>= 0); the same seed gives the same files."),
    seeds: Optional[str] = typer.Option(
        None,
        "--seeds",
        metavar="A-B",
        help="Dataset mode: subject seeds A to B (inclusive), or a comma list of seeds and ranges; writes "
        "OUTPUT/subject_<seed>/ and OUTPUT/manifest.json, skipping subjects already complete.",
    ),
    output: Path = options.output("Subject folder to write (replaced whole), or with --seeds the dataset folder."),
    res: Optional[int] = options.image_size(
        None, "Image width and height in pixels (default 512; 256 with --seeds).", "--res"
    ),
    novel_views: Optional[int] = typer.Option(
        None,
        "--novel-views",
        min=0,
        max=1024,
        help="Ground-truth views of the input pose, 0: none (default 12; 8 with --seeds).",
    ),
    novel_poses: Optional[int] = typer.Option(
        None, "--novel-poses", min=0, max=1024, help="Ground-truth poses, 3 cameras each (0: none; default 8)."
    ),
    appearance: Optional[str] = typer.Option(
        None,
        "--appearance",
        help="albedo: headlight shading, the same colour in every pose (default); lit: lights fixed in the world, "
        "ambient occlusion per pose, specular highlights (default with --seeds); mixed (dataset mode): each "
        "subject lit or albedo, drawn from its seed.",
    ),
    wardrobe: Optional[str] = typer.Option(
        None,
        "--wardrobe",
        help="default: a casual suit by gender, shoes01 and short hair (default); full: every shipped suit, shoe and "
        "hair style, wider patterns and colours (default with --seeds); train / heldout: full without / with only "
        "the held-out suits and hair (docs/synth.md).",
    ),
    motions: Optional[list[Path]] = typer.Option(
        None,
        "--motions",
        help="Dataset mode: motion files or folders of them (CMU .bvh, .amc with its .asf beside it, motion.npz) "
        "whose random frames are target poses, besides the built-in motions; repeatable.",
    ),
    jobs: int = typer.Option(1, "--jobs", min=1, max=256, help="Dataset mode: worker processes (one thread each)."),
) -> None:
    """Write a synthetic subject (4 input views + its true body.json, novel views and poses), or a dataset of them."""
    from dlacli.errors import DlaInputError

    if (seed is None) == (seeds is None):
        raise DlaInputError("--seed/--seeds", "give exactly one: --seed S (one subject) or --seeds A-B (a dataset)")
    # the options given; the stage's own defaults fill the rest (one subject and a dataset differ)
    given = dict(res=res, novel_views=novel_views, novel_poses=novel_poses, appearance=appearance, wardrobe=wardrobe)
    given = {key: value for key, value in given.items() if value is not None}
    if seeds is not None:
        from dlacli.data.dataset import DatasetSettings, motion_files, synth_dataset

        subjects = parse_seeds(seeds)
        settings = DatasetSettings(**given, motions=motion_files(motions or []))
        synth_dataset(subjects, output, settings, jobs=jobs, progress=lambda msg: typer.echo(msg, err=True))
        typer.echo(str(output))
        return
    if motions:
        raise DlaInputError("--motions", "is for dataset mode (--seeds); one subject's novel poses are its own")
    if jobs != 1:
        raise DlaInputError("--jobs", "is for dataset mode (--seeds)")
    from dlacli.cli.progress import status
    from dlacli.data.synth import SUBJECT_LAYOUT
    from dlacli.data.synth import synth as run
    from dlacli.io.atomic import check_outputs

    check_outputs(folders=[(output, SUBJECT_LAYOUT)])
    with status("dla synth") as update:
        path = run(seed, output, progress=update, **given)
    typer.echo(str(path))


def register(app: typer.Typer) -> None:
    app.command("synth")(synth)
