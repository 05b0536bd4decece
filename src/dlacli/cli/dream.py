"""`dla dream`: one photo of a person -> a view folder (input view + 3 novel views) + body fit."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli import options
from dlacli.limits import DEFAULT_PRIOR, FIT_STEPS
from dlacli.stages.dream.backends import BACKENDS, DEFAULT

_BACKEND_HELP = "How the novel views are made (dlacli.stages.dream.backends): " + "; ".join(
    f"'{b.name}'{' (default)' if b.name == DEFAULT else ''}: {b.about}" for b in BACKENDS.values()
)


def dream(
    photo: Path = typer.Argument(
        ...,
        metavar="PHOTO",
        help="Photo of one person (PNG/JPEG; RGBA: alpha = person mask). A sample ships with dla: see below.",
    ),
    output: Path = options.output("View folder to write (replaced whole, written atomically)."),
    backend: str = typer.Option(DEFAULT, "--backend", help=_BACKEND_HELP),
    keypoints: Optional[Path] = typer.Option(
        None, "--keypoints", help="COCO-17 keypoints JSON of the person (default: detected with MediaPipe Pose)."
    ),
    mask: Optional[Path] = typer.Option(
        None,
        "--mask",
        help="Person mask PNG when the photo has no alpha channel (default: detected with MediaPipe's person "
        "segmentation).",
    ),
    res: int = options.image_size(512, "Width and height of the square views in pixels.", "--res", minimum=64),
    model: Optional[str] = typer.Option(
        None,
        "--model",
        help="Diffusion backend: a local diffusers pipeline folder or a hub id already in the local cache (default "
        "Wan-AI/Wan2.1-VACE-1.3B-diffusers). Nothing is downloaded.",
    ),
    steps: int = typer.Option(50, "--steps", min=1, max=1000, help="Diffusion backend: sampling steps."),
    frames: int = typer.Option(
        80,
        "--frames",
        min=4,
        max=1024,
        help="Diffusion backend: frames of the 360-degree orbit (multiple of 4; views are frames N/4, N/2, 3N/4).",
    ),
    seed: int = options.seed("Diffusion backend: noise seed.", default=0),
    fit_steps: int = typer.Option(
        FIT_STEPS, "--fit-steps", min=3, max=100_000, help="Optimisation steps of the body fit."
    ),
    prior: Optional[str] = typer.Option(
        None,
        "--prior",
        help="Body backend: what fills the surface the photo does not show: 'shipped' (the completion network "
        "trained by dla and shipped in the package), 'none' (the hand-written rule: mirror, then the nearest "
        "well-seen colour, blurred) or a checkpoint folder or hash from `dla train --method completion`. Default: "
        f"{DEFAULT_PRIOR}.",
    ),
    landmarks: str = options.landmarks(),
) -> None:
    """Dream novel views of a person from one photo: fit the body, then write a view folder with
    the photo (azimuth 0) and views at azimuths 90, 180, 270, plus body.json and fit_overlay.png.

    Sample photo: python -c "from dlacli.paths import sample_photo; print(sample_photo())"
    """
    from dlacli.cli.progress import status
    from dlacli.io.atomic import check_outputs
    from dlacli.io.views import LAYOUT

    check_outputs(folders=[(output, (*LAYOUT, "fit_overlay.png"))], inputs=[photo, keypoints, mask])
    from dlacli.stages.dream.backends import get

    detects = get(backend).load is None  # a backend that loads a model first reads the photo after it
    detection = _start_detection(photo, mask, keypoints, landmarks) if detects else None
    from dlacli.stages.dream.views import dream as run  # imports torch: the detection runs meanwhile

    warnings: list[str] = []

    try:
        with status("dla dream") as update:

            def report(message: str) -> None:  # warnings outlive the spinner: printed after it
                if message.startswith("warning: "):
                    warnings.append(message)
                update(message)

            path = run(
                photo,
                output,
                backend=backend,
                keypoints=keypoints,
                mask=mask,
                res=res,
                model=model,
                steps=steps,
                frames=frames,
                seed=seed,
                fit_steps=fit_steps,
                progress=report,
                prior=prior,
                detection=detection,
                landmarks=landmarks,
            )
    finally:
        if detection is not None:
            detection.cancel()  # a no-op once its result was taken
    for line in warnings:
        typer.echo(line, err=True)
    typer.echo(str(path))


def _start_detection(photo: Path, mask: Optional[Path], keypoints: Optional[Path], landmarks: str):
    """A `BackgroundDetection` of the photo when dream will need the detector (no --mask or no
    --keypoints, and the photo has no alpha channel standing in for the mask), else None; None
    too when the photo cannot be read (dream then reports that itself, in its own order)."""
    from dlacli.errors import DlaInputError
    from dlacli.io.detect import BackgroundDetection
    from dlacli.io.photo import read_photo

    try:
        image, alpha, kps = read_photo(photo, mask_path=mask, keypoints_path=keypoints, notes=[])
    except DlaInputError:
        return None
    if alpha is not None and kps is not None:
        return None
    return BackgroundDetection(image, alpha, landmarks)


def register(app: typer.Typer) -> None:
    app.command("dream")(dream)
