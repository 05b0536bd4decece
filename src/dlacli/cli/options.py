"""The options the commands share, written once: a factory per recurring option (avatar,
checkpoint, seed, gaussians, motion, output files with their suffixes, frame rates, image sizes)
returns the typer parameter with its help text, range and parser, and the callbacks below are the
one place each check is made. Ranges and defaults come from `dlacli.limits` (torch-free: building
the options loads no stage).

`finite` refuses NaN and infinities in float options (typer's ranges have let NaN through: every
comparison with NaN is false).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Optional

import typer

from dlacli.errors import DlaInputError
from dlacli.limits import (
    DEFAULT_GAUSSIANS,
    DEFAULT_LANDMARKS,
    LANDMARKS,
    MAX_FPS,
    MAX_GAUSSIANS,
    MAX_IMAGE_SIZE,
    MAX_SEED,
    MIN_GAUSSIANS,
    MIN_IMAGE_SIZE,
    MIN_RESAMPLE_FPS,
    MIN_VIDEO_FPS,
)

CHECKPOINT_HELP = (
    "The learned decoder's checkpoint folder, when it is not in the checkpoints cache "
    "(~/.cache/dla/checkpoints) under the hash the avatar records."
)
SAMPLE_SEED_HELP = "Seed of the sample points (default: the avatar's own)."
MOTION_SPEC = (
    "a motion.npz, AMASS .npz, BVH, ASF/AMC (.amc with its .asf beside it, or CLIP.amc:SKELETON.asf), "
    "or a built-in name: idle, walk, turnaround, wave"
)
RESAMPLE_HELP = "Resample the motion to this frame rate (default: the motion's own)."


# ------------------------------------------------------------------------------------------------
# callbacks: the checks


def finite(value: float | None) -> float | None:
    """A float option must be a finite number (or absent)."""
    if value is not None and not math.isfinite(value):
        raise typer.BadParameter(f"must be a finite number, got {value}")
    return value


def _either(words: Sequence[str]) -> str:
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} or {words[-1]}"


def _a(word: str) -> str:
    return "an" if word[:1].lower() in "aeiou" else "a"


def check_suffix(path: Path, suffixes: Sequence[str], what: str, hint: str = "") -> Path:
    """The one suffix check of every file a command writes: `path` must end in one of `suffixes`
    (lower case, with the dot; any case in the name), else a DlaInputError naming the file.
    `what` names the content ("video", "avatar"); `hint` is added to the message."""
    suffix = path.suffix.lower()
    if suffix in suffixes:
        return path
    use, a_what = _either(suffixes), f"{_a(what)} {what}"
    if not suffix:
        raise DlaInputError(path, f"has no suffix; use {use} for {a_what}{hint}")
    raise DlaInputError(path, f"{path.suffix!r} is not {a_what} format dla writes; use {use}{hint}")


def _parse_gaussians(value: str | None, allow_auto: bool) -> int | str | None:
    """--gaussians: an integer in [MIN_GAUSSIANS, MAX_GAUSSIANS], or (where `allow_auto`) "auto"
    (dlacli.stages.budget); None when the option is absent."""
    if value is None:
        return None
    if allow_auto and value.strip().lower() == "auto":
        return "auto"
    try:
        n = int(value)
    except ValueError:
        expected = "an integer or 'auto'" if allow_auto else "an integer"
        raise typer.BadParameter(f"expected {expected}, got {value[:40]!r}") from None
    if not MIN_GAUSSIANS <= n <= MAX_GAUSSIANS:
        raise typer.BadParameter(f"{n} is not in the range {MIN_GAUSSIANS}<=x<={MAX_GAUSSIANS}")
    return n


def gaussian_count(value: str | None) -> int | str | None:
    """--gaussians N|auto (render, animate, lift)."""
    return _parse_gaussians(value, allow_auto=True)


def gaussian_number(value: str | None) -> int | None:
    """--gaussians N (export, view: no camera to budget for)."""
    return _parse_gaussians(value, allow_auto=False)


@contextlib.contextmanager
def naming(**files) -> Iterator[None]:
    """Errors that stages raise about an in-memory part ("views", "pose", "phenotype", "avatar")
    name the user's file instead, e.g. `naming(pose=views / "body.json")`; the part's name stays
    at the front of the problem when it says more than the file does."""
    try:
        yield
    except DlaInputError as err:
        target = files.get(err.where or "")
        if target is None:
            raise
        problem = err.problem if err.where in ("views", "avatar") else f"{err.where}: {err.problem}"
        raise DlaInputError(target, problem) from None


def naming_avatar(path: Path, **files) -> contextlib.AbstractContextManager[None]:
    """`naming` for an avatar file: errors about the avatar, its pose and its phenotype name it."""
    return naming(avatar=path, pose=path, phenotype=path, **files)


def auto_note(choice, default: bool = False) -> str:
    """The line `--gaussians auto` (or, `default`, no --gaussians on an avatar with a budget) prints
    on stderr (a `dlacli.stages.budget.BudgetChoice`)."""
    recorded = choice.rule == "recorded"
    how = "from the avatar's lift-time budget" if recorded else "by sampling noise (no budget recorded)"
    what = "the avatar's budget" if default else "--gaussians auto"
    return f"note: {what}: {choice.count:,} Gaussians for a person {choice.subject_px:.0f} px tall, {how}"


# ------------------------------------------------------------------------------------------------
# factories: `name: type = options.x(...)` in a command's signature


def avatar(help: str = "avatar.npz", metavar: str = "AVATAR") -> Any:
    """The avatar argument."""
    return typer.Argument(..., metavar=metavar, help=help)


def checkpoint(help: str = CHECKPOINT_HELP) -> Any:
    """--checkpoint FOLDER (Optional[Path])."""
    return typer.Option(None, "--checkpoint", help=help)


def seed(help: str = SAMPLE_SEED_HELP, default: int | None = None, maximum: int = MAX_SEED) -> Any:
    """--seed S in [0, maximum] (Optional[int] when there is no default)."""
    return typer.Option(default, "--seed", min=0, max=maximum, help=help)


def gaussians(
    auto_cameras: str | None = None, what: str = "Gaussians sampled from the avatar", help: str | None = None
) -> Any:
    """--gaussians N (Optional[str]; the parsed value is an int or None), or with `auto_cameras`
    (the cameras `auto` sizes the person in) N|auto. `help` replaces the help text (a command whose
    count means something else, e.g. lift's or a benchmark's)."""
    auto = auto_cameras is not None
    if help is None:
        help = f"{what}, half uniformly in UV, half on the surface "
        if auto:
            help += (
                f"(default: the avatar's recorded budget scaled to the person's size in {auto_cameras}, else the "
                f"count it was lifted with, else {DEFAULT_GAUSSIANS:,})"
            )
        else:
            help += f"(default: the count the avatar was lifted with, its budget, else {DEFAULT_GAUSSIANS:,})"
        if auto:
            help += (
                f"; 'auto': the count lift --gaussians auto recorded, scaled to the person's size in {auto_cameras}, "
            )
            help += (
                "else the fewest whose sampling noise costs under 0.2 dB (docs/benchmarks.md, 'The Gaussian budget')"
            )
        help += "."
    parse = gaussian_count if auto else gaussian_number
    return typer.Option(None, "--gaussians", callback=parse, metavar="N|auto" if auto else "N", help=help)


def motion_argument(help: str = f"The motion: {MOTION_SPEC}.", metavar: str = "MOTION") -> Any:
    """The motion spec argument (str)."""
    return typer.Argument(..., metavar=metavar, help=help)


def motion(use: str, *, short: bool = False) -> Any:
    """--motion SPEC (Optional[str]); `use` says what the motion does here, `short` adds -m."""
    return typer.Option(None, "--motion", *(("-m",) if short else ()), help=f"{use}: {MOTION_SPEC}.")


def allow_missing_joints() -> Any:
    """--allow-missing-joints (bool)."""
    help = "Accept a motion file lacking joints its skeleton family always has (e.g. a renamed LeftUpLeg): "
    return typer.Option(False, "--allow-missing-joints", help=help + "those anny bones stay at rest.")


def resample_fps(help: str = RESAMPLE_HELP) -> Any:
    """--fps that resamples a motion (Optional[float])."""
    return typer.Option(None, "--fps", min=MIN_RESAMPLE_FPS, max=MAX_FPS, callback=finite, help=help)


def video_fps(default: float | None, help: str) -> Any:
    """--fps of a video a command writes (float, or Optional[float] with default None)."""
    return typer.Option(default, "--fps", min=MIN_VIDEO_FPS, max=MAX_FPS, callback=finite, help=help)


def _landmarks_callback(value: str) -> str:
    if value not in LANDMARKS:
        raise DlaInputError("--landmarks", f"expected {_either(LANDMARKS)}, got {value!r}")
    return value


def landmarks() -> Any:
    """--landmarks lite|full|heavy (str): MediaPipe Pose's landmark model (dlacli.io.detect)."""
    return typer.Option(
        DEFAULT_LANDMARKS,
        "--landmarks",
        callback=_landmarks_callback,
        help="MediaPipe Pose's landmark model: 'full' (default, in the mediapipe wheel), 'lite' (faster) or 'heavy' "
        "(more accurate, slower); lite and heavy are installed by scripts/install-landmarks.sh, never downloaded.",
    )


def image_size(
    default: int | None, help: str, flag: str = "--size", minimum: int = MIN_IMAGE_SIZE, maximum: int = MAX_IMAGE_SIZE
) -> Any:
    """A square image or video side in pixels (int, or Optional[int] with default None)."""
    return typer.Option(default, flag, min=minimum, max=maximum, help=help)


def _suffix_callback(suffixes: Sequence[str], what: str):
    if not suffixes:
        return None

    def check(value: Optional[Path]) -> Optional[Path]:
        return None if value is None else check_suffix(value, suffixes, what)

    return check


def output(
    help: str, suffixes: Sequence[str] = (), what: str = "", required: bool = True, default: Path | None = None
) -> Any:
    """-o/--output: the file or folder the command writes (Path; Optional[Path] unless `required`
    or given a `default`). With `suffixes` the name is checked as it is parsed (`check_suffix`;
    `what` names the content)."""
    check = _suffix_callback(suffixes, what)
    value = default if default is not None else ... if required else None
    return typer.Option(value, "--output", "-o", help=help, callback=check)


def side_output(flag: str, help: str, suffixes: Sequence[str], what: str) -> Any:
    """An optional second file the command also writes, e.g. --video (Optional[Path]), suffix-checked."""
    return typer.Option(None, flag, help=help, callback=_suffix_callback(suffixes, what))
