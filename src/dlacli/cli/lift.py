"""`dla lift`: a view folder -> avatar.npz (+ Gaussians .ply, contact sheet)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Optional

import typer

from dlacli.cli.options import gaussian_count
from dlacli.limits import DEFAULT_GAUSSIANS, LIFT_RESOLUTION, LIFT_STEPS

# `dlacli.stages.lift.LiftConfig`'s defaults, from the torch-free limits module (loading the CLI for
# `dla --version` or `dla info` does not import the stage and torch).
_DEFAULTS = SimpleNamespace(steps=LIFT_STEPS, resolution=LIFT_RESOLUTION, gaussians=DEFAULT_GAUSSIANS)


def lift(
    views: Path = typer.Argument(..., metavar="VIEWS", help="View folder: transforms.json, images, body.json."),
    output: Path = typer.Option(..., "--output", "-o", help="avatar.npz to write; a contact sheet PNG is written beside it."),
    ply: Optional[Path] = typer.Option(None, "--ply", help="Also write the unstructured pose-space Gaussians as a 3DGS .ply."),
    steps: Optional[int] = typer.Option(None, "--steps", min=0, max=100_000, help=f"Refinement steps against the input views (unproject: default {_DEFAULTS.steps}, 0 = mesh unprojection only; learned: default 0, N refines Z through the frozen decoder); more is slower and closer."),
    method: str = typer.Option("unproject", "--method", help="Encoder into the latent Z: 'unproject' (mesh unprojection, no weights) or 'learned' (U-Net + cross-attention encoder + GPD from --checkpoint)."),
    checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="With --method learned: the network checkpoint folder (`dla train`'s RUN/ckpt-N/generator) or its hash in the checkpoints cache."),
    resolution: int = typer.Option(_DEFAULTS.resolution, "--resolution", min=16, max=2048, help="UV resolution of the Gaussian map Z."),
    gaussians: str = typer.Option(str(_DEFAULTS.gaussians), "--gaussians", callback=gaussian_count, metavar="N|auto", help="Gaussians sampled from Z while refining; 'auto': refine with 131,072, then record the fewest (4,096 ... 262,144) whose re-renders of the input views score within 0.2 dB masked PSNR of the best (docs/benchmarks.md, 'The Gaussian budget')."),
    seed: int = typer.Option(0, "--seed", min=0, max=2**32 - 1, help="Seed of the Gaussian sample points."),
    view_colour: bool = typer.Option(True, "--view-colour/--no-view-colour", help="Measure how the views' colours fall off with the viewing angle and, where they do (|k| >= 0.05), model it (decoder 'view-cosine', docs/lift.md); --no-view-colour: colour never depends on the view."),
    allow_outside: bool = typer.Option(False, "--allow-outside", help="Read images that transforms.json names outside the view folder (absolute paths, '..', links out)."),
) -> None:
    """Lift a view folder into an animatable avatar (avatar.npz).

    Unstructured pixel-aligned Gaussians, mesh unprojection into the UV-aligned code Z, then
    optional refinement through skinning and splatting against the input views.
    """
    from PIL import Image

    from dlacli.cli.options import naming
    from dlacli.cli.progress import progress_bar
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import atomic_path, check_outputs, output_group
    from dlacli.io.avatar import write_avatar
    from dlacli.io.ply import write_ply
    from dlacli.io.views import read_transforms, read_views, view_files
    from dlacli.avatar.codec import check_encoder
    from dlacli.stages.lift import MAX_VIEWS, LiftConfig
    from dlacli.stages.lift import lift as run_lift

    check_encoder(method)
    learned = method == "learned"
    if learned and checkpoint is None:
        raise DlaInputError("--checkpoint", "--method learned needs the network's checkpoint (dla train)")
    if not learned and checkpoint is not None:
        raise DlaInputError("--checkpoint", f"--method {method} takes no checkpoint")
    if steps is None:
        steps = 0 if learned else _DEFAULTS.steps
    if output.suffix.lower() != ".npz":
        raise DlaInputError(output, "the avatar is an .npz file")
    if ply is not None and ply.suffix.lower() != ".ply":
        raise DlaInputError(ply, "the Gaussians are a .ply file")
    sheet = output.with_name(output.stem + "_contact.png")
    novel_dir = views / "novel_views" if views.is_dir() else None  # synth's ground truth, when present
    if novel_dir is not None and not (novel_dir / "transforms.json").is_file():
        novel_dir = None
    novel_files = view_files(novel_dir, allow_outside) if novel_dir is not None else []
    ckpt_files = [checkpoint] if checkpoint is not None and checkpoint.exists() else []
    check_outputs(files=[output, sheet, ply], inputs=[views, *view_files(views, allow_outside), *novel_files, *ckpt_files])
    n_views = len(read_transforms(views)["file_paths"])
    if n_views > MAX_VIEWS:
        raise DlaInputError(views, f"has {n_views} views; lift takes at most {MAX_VIEWS} (the method uses 4)")
    auto = gaussians == "auto"
    cfg = LiftConfig(steps=steps, resolution=resolution, gaussians=_DEFAULTS.gaussians if auto else gaussians, seed=seed,
                     view_colour=view_colour)  # fmt: skip
    view_set = read_views(views, allow_outside=allow_outside)
    novel = read_views(novel_dir, require_body=False, allow_outside=allow_outside) if novel_dir is not None else None
    body = views / "body.json" if views.is_dir() else views.with_name("body.json")
    with naming(views=views, pose=body, phenotype=body), progress_bar("refining", steps) as update:
        report = lambda i, loss: update(i + 1, note=f"loss {loss:.4f}")  # noqa: E731
        if learned:
            from dlacli.stages.learned import lift_learned

            result = lift_learned(view_set, str(checkpoint), steps=steps, progress=report, novel=novel)
        else:
            result = run_lift(view_set, cfg, progress=report, novel=novel)
    if auto:
        from dlacli.stages.budget import choose_for_views

        with naming(views=views, pose=body, phenotype=body):
            result.avatar, choice = choose_for_views(result.avatar, view_set)
        typer.echo(f"note: --gaussians auto: {choice.count:,} Gaussians (input views, masked PSNR "
                   f"{choice.scores[choice.count]:.2f} dB, best {max(choice.scores.values()):.2f})", err=True)  # fmt: skip
    falloff = result.avatar.extra.get("lift", {}).get("view_falloff")
    if falloff:
        typer.echo(f"note: {views}: colour falls off with the viewing angle, k = {falloff:.2f} "
                   "(colour x (1 - k + k cos)): decoder view-cosine", err=True)  # fmt: skip
    if result.novel_view is not None:
        from dlacli.bench.metrics import masked_psnr

        score = masked_psnr(*result.novel_view)
        typer.echo(f"note: {novel_dir}: first novel view, masked PSNR {score:.2f} dB (fifth column of {sheet.name})", err=True)
    with output_group():  # the avatar, its contact sheet and the .ply land together or not at all
        if ply is not None:
            write_ply(result.unstructured, ply)
        with atomic_path(sheet) as tmp:
            Image.fromarray(result.contact_sheet).save(tmp)
        write_avatar(result.avatar, output)
    if learned:  # animate, render and edit find the decoder by the hash the avatar records
        from dlacli.avatar.checkpoint import install_checkpoint, resolve_checkpoint

        install_checkpoint(resolve_checkpoint(str(checkpoint)))
    typer.echo(str(output))


def register(app: typer.Typer) -> None:
    app.command("lift")(lift)
