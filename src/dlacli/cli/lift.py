"""`dla lift`: a view folder -> avatar.npz (+ Gaussians .ply, contact sheet)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli import options
from dlacli.limits import (
    BUDGET_LADDER,
    BUDGET_TOLERANCE_DB,
    LIFT_STEPS,
    MAX_LIFT_RESOLUTION,
    MAX_LIFT_STEPS,
    MIN_VIEW_FALLOFF,
)
from dlacli.stages.lift.methods import METHODS
from dlacli.stages.lift.methods.unproject import DEFAULTS

# the options that set a field of the method's config, by field name
_FIELDS = {
    "steps": "--steps",
    "checkpoint": "--checkpoint",
    "resolution": "--resolution",
    "gaussians": "--gaussians",
    "seed": "--seed",
    "view_colour": "--view-colour",
}
_KNOWN = "; ".join(f"'{m.name}' ({m.about})" for m in METHODS.values())
_METHOD_HELP = (
    f"The lift method, NAME[:KEY=VALUE,...] (dlacli.stages.lift.methods): {_KNOWN}. Options below set its keys."
)
_STEPS_HELP = (
    f"Refinement steps against the input views (unproject: default {LIFT_STEPS}, 0 = mesh unprojection "
    "only; learned: default 0, N refines Z through the frozen decoder); more is slower and closer."
)
_CHECKPOINT_HELP = (
    "With --method learned: the network checkpoint folder (`dla train`'s RUN/ckpt-N/generator) or its hash "
    "in the checkpoints cache."
)
_GAUSSIANS_HELP = (
    f"'auto' (default): refine with {DEFAULTS['gaussians']:,} Gaussians sampled from Z and record them as the "
    "budget render, animate, view and export draw by default; with --steps 0, record the fewest "
    f"({BUDGET_LADDER[0]:,} ... {BUDGET_LADDER[-1]:,}) whose re-renders of the input views score within "
    f"{BUDGET_TOLERANCE_DB:g} dB masked PSNR of the best (docs/lift.md); N: refine with and record N, no budget."
)
_VIEW_COLOUR_HELP = (
    f"Measure how the views' colours fall off with the viewing angle and, where they do (|k| >= {MIN_VIEW_FALLOFF:g}), "
    "model it (decoder 'view-cosine', docs/lift.md); --no-view-colour: colour never depends on the view."
)


def lift(
    ctx: typer.Context,
    views: Path = typer.Argument(..., metavar="VIEWS", help="View folder: transforms.json, images, body.json."),
    output: Path = options.output(
        "avatar.npz to write; a contact sheet PNG is written beside it.", (".npz",), "avatar"
    ),
    ply: Optional[Path] = options.side_output(
        "--ply", "Also write the unstructured pose-space Gaussians as a 3DGS .ply.", (".ply",), "Gaussians file"
    ),
    steps: Optional[int] = typer.Option(None, "--steps", min=0, max=MAX_LIFT_STEPS, help=_STEPS_HELP),
    method: str = typer.Option("unproject", "--method", help=_METHOD_HELP),
    checkpoint: Optional[Path] = options.checkpoint(_CHECKPOINT_HELP),
    resolution: int = options.image_size(
        DEFAULTS["resolution"], "UV resolution of the Gaussian map Z.", "--resolution", maximum=MAX_LIFT_RESOLUTION
    ),
    gaussians: Optional[str] = options.gaussians("the input views", help=_GAUSSIANS_HELP),
    seed: int = options.seed("Seed of the Gaussian sample points.", default=DEFAULTS["seed"]),
    view_colour: bool = typer.Option(True, "--view-colour/--no-view-colour", help=_VIEW_COLOUR_HELP),
    allow_outside: bool = typer.Option(
        False,
        "--allow-outside",
        help="Read images that transforms.json names outside the view folder (absolute paths, '..', links out).",
    ),
) -> None:
    """Lift a view folder into an animatable avatar (avatar.npz).

    Unstructured pixel-aligned Gaussians, mesh unprojection into the UV-aligned code Z, then
    optional refinement through skinning and splatting against the input views.
    """
    from PIL import Image

    from dlacli.cli.progress import progress_bar
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import atomic_path, check_outputs, output_group
    from dlacli.io.avatar import write_avatar
    from dlacli.io.ply import write_ply
    from dlacli.io.views import read_transforms, read_views, view_files
    from dlacli.limits import MAX_VIEWS

    auto = gaussians in (None, "auto")  # the default: measure and record the budget
    ckpt = None if checkpoint is None else str(checkpoint)
    flags = dict(
        steps=steps,
        checkpoint=ckpt,
        resolution=resolution,
        gaussians=None if auto else gaussians,
        seed=seed,
        view_colour=view_colour,
    )
    spec = _spec(method, {k: v for k, v in flags.items() if v is not None and _on_command_line(ctx, k)})
    auto = auto and "gaussians" not in spec.given  # a count in the method spec wins too
    steps = getattr(spec.config, "steps", 0)  # the progress bar's length: a method without refinement has none
    sheet = output.with_name(output.stem + "_contact.png")
    novel_dir = views / "novel_views" if views.is_dir() else None  # synth's ground truth, when present
    if novel_dir is not None and not (novel_dir / "transforms.json").is_file():
        novel_dir = None
    novel_files = view_files(novel_dir, allow_outside) if novel_dir is not None else []
    ckpt = spec.options().get("checkpoint")  # the network's files are inputs: no output may land on them
    ckpt_files = [Path(ckpt)] if ckpt and Path(ckpt).exists() else []
    check_outputs(
        files=[output, sheet, ply], inputs=[views, *view_files(views, allow_outside), *novel_files, *ckpt_files]
    )
    n_views = len(read_transforms(views)["file_paths"])
    if n_views > MAX_VIEWS:
        raise DlaInputError(views, f"has {n_views} views; lift takes at most {MAX_VIEWS} (the method uses 4)")
    view_set = read_views(views, allow_outside=allow_outside)
    novel = read_views(novel_dir, require_body=False, allow_outside=allow_outside) if novel_dir is not None else None
    body = views / "body.json" if views.is_dir() else views.with_name("body.json")
    with options.naming(views=views, pose=body, phenotype=body), progress_bar("refining", steps) as update:
        report = lambda i, loss: update(i + 1, note=f"loss {loss:.4f}")  # noqa: E731
        result = spec.lift(view_set, progress=report, novel=novel)
    if auto:
        from dlacli.stages.budget import choose_for_views

        # a refined avatar is fitted to the points it was refined at: other counts read Z where the
        # loss never looked and score lower, so its budget is that count (docs/lift.md step 5)
        refined = result.avatar.extra.get("samples", {}).get("count") if steps else None
        with options.naming(views=views, pose=body, phenotype=body):
            # the network the avatar's decoder names (the residual lift's network is no decoder)
            decoder_ckpt = ckpt if result.avatar.checkpoint else None
            result.avatar, choice = choose_for_views(
                result.avatar, view_set, checkpoint=decoder_ckpt, **({"counts": (refined,)} if refined else {})
            )
        typer.echo(
            f"note: --gaussians auto: {choice.count:,} Gaussians (input views, masked PSNR "
            f"{choice.scores[choice.count]:.2f} dB, best {max(choice.scores.values()):.2f})",
            err=True,
        )
    falloff = result.avatar.extra.get("lift", {}).get("view_falloff")
    if falloff:
        typer.echo(
            f"note: {views}: colour falls off with the viewing angle, k = {falloff:.2f} "
            "(colour x (1 - k + k cos)): decoder view-cosine",
            err=True,
        )
    if result.novel_view is not None:
        from dlacli.bench.metrics import masked_psnr

        score = masked_psnr(*result.novel_view)
        typer.echo(
            f"note: {novel_dir}: first novel view, masked PSNR {score:.2f} dB (fifth column of {sheet.name})", err=True
        )
    with output_group():  # the avatar, its contact sheet and the .ply land together or not at all
        if ply is not None:
            write_ply(result.unstructured, ply)
        with atomic_path(sheet) as tmp:
            Image.fromarray(result.contact_sheet).save(tmp)
        write_avatar(result.avatar, output)
    spec.install()  # e.g. animate, render and edit find a learned avatar's decoder by the hash it records
    typer.echo(str(output))


def _on_command_line(ctx: typer.Context, name: str) -> bool:
    """Whether option `name` was given (not left at its default)."""
    source = ctx.get_parameter_source(name)
    return source is not None and source.name not in ("DEFAULT", "DEFAULT_MAP")


def _spec(text: str, options: dict):
    """The method spec `text` with the options given as flags (a key the spec sets otherwise, or
    one the method does not take, is a one-line error naming the flag), then `dla lift`'s own
    defaults (`Method.lift_defaults`) where neither says."""
    from dlacli.errors import DlaInputError
    from dlacli.stages.lift.methods import parse_method

    spec = parse_method(text, fill=options, flags=_FIELDS)
    for key, value in options.items():
        if not hasattr(spec.config, key):
            raise DlaInputError(_FIELDS[key], f"--method {spec.name} takes no {key}")
        if getattr(spec.config, key) != value:
            raise DlaInputError(_FIELDS[key], f"--method {text[:80]} already sets {key}")
    defaults = {k: v for k, v in spec.method.lift_defaults.items() if k not in spec.given}
    return spec.with_options("--method", **defaults) if defaults else spec


def register(app: typer.Typer) -> None:
    app.command("lift")(lift)
