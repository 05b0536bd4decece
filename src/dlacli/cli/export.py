"""`dla export`: the avatar's own Gaussians as .ply / .spz / .splat / .glb (or a rigged USD)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli import options
from dlacli.cli.options import check_suffix, naming_avatar
from dlacli.limits import SPLAT_SUFFIXES, USD_SUFFIXES


def export(
    avatar: Path = options.avatar(),
    output: Optional[Path] = options.output(
        "Output file: .ply (3DGS PLY), .spz (Niantic SPZ v3), .splat (antimatter15) or .glb "
        "(glTF KHR_gaussian_splatting); with --rig a .usdc, .usda or .usd.",
        required=False,
    ),
    pose: Optional[str] = typer.Option(
        None,
        "--pose",
        help="rest: the zero pose (A-pose, pelvis at the origin, facing -Y); canonical: the input pose's joint "
        "rotations, upright at the origin facing -Y (no root rotation or translation); input (default): the pose "
        "of the views the avatar was lifted from, as `dla render` draws it.",
    ),
    motion: Optional[str] = options.motion(
        "Pose the avatar at a frame of this motion (--frame) or at all of them (--sequence)"
    ),
    frame: Optional[int] = typer.Option(None, "--frame", min=0, help="The motion frame to export (0 = first)."),
    sequence: Optional[Path] = typer.Option(
        None,
        "--sequence",
        help="Folder for one file per motion frame, frame_0000.ply, frame_0001.ply, ... (instead of -o; the suffix "
        "follows --format).",
    ),
    fmt: str = typer.Option("ply", "--format", help="File format of --sequence: ply, spz, splat or glb."),
    up: Optional[str] = typer.Option(
        None,
        "--up",
        help="y (default): upright in common splat viewers (3DGS/COLMAP axes for .ply/.spz/.splat as SuperSplat and "
        "PlayCanvas show them; glTF's own +Y up for .glb); z: dla's world as is (+Z up, facing -Y; not for .glb).",
    ),
    gaussians: Optional[str] = options.gaussians(),
    seed: Optional[int] = options.seed(),
    checkpoint: Optional[Path] = options.checkpoint(),
    fps: Optional[float] = options.resample_fps("Resample the motion to this frame rate first (default: its own)."),
    rig: bool = typer.Option(
        False,
        "--rig",
        help="Write a rigged USD instead (skeleton + skinned mesh for Blender; -o .usdc/.usda/.usd); with --motion "
        "the joint animation is included.",
    ),
    allow_missing_joints: bool = options.allow_missing_joints(),
) -> None:
    """Export the avatar's own Gaussians (what `dla render` splats) for splat viewers and tools."""
    from dlacli.cli.progress import progress_bar
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import atomic_dir, check_outputs
    from dlacli.io.avatar import read_avatar
    from dlacli.stages.export import POSES, UPS
    from dlacli.stages.motion.source import load_motion, split_spec

    if pose is not None and pose not in POSES:
        raise DlaInputError("--pose", f"unknown pose {pose!r} (use one of {', '.join(POSES)})")
    if up is not None and up not in UPS:
        raise DlaInputError("--up", f"unknown up axis {up!r} (use y or z)")
    if rig:
        if output is None:
            raise DlaInputError("--output", "--rig writes a USD file: give -o with .usdc, .usda or .usd")
        check_suffix(output, USD_SUFFIXES, "rigged USD")
        for flag, given in (("--sequence", sequence), ("--frame", frame), ("--pose", pose), ("--up", up)):
            if given is not None:
                raise DlaInputError(
                    flag,
                    "does not apply to --rig (the rig is bound in the rest pose, +Z up; --motion adds its animation)",
                )
    else:
        if (output is None) == (sequence is None):
            raise DlaInputError("--output", "give either -o FILE or --sequence FOLDER")
        if output is not None:
            usd = output.suffix.lower() in USD_SUFFIXES
            hint = " (a rigged USD needs --rig; `dla animate` writes Gaussian animations)" if usd else ""
            check_suffix(output, SPLAT_SUFFIXES, "splat", hint)
        if f".{fmt.lower()}" not in SPLAT_SUFFIXES:
            raise DlaInputError("--format", f"unknown format {fmt!r} (use ply, spz, splat or glb)")
        if motion is None and (frame is not None or sequence is not None):
            raise DlaInputError("--frame" if frame is not None else "--sequence", "needs --motion")
        if motion is not None:
            if pose is not None:
                raise DlaInputError(
                    "--pose", "a motion gives the pose: use --pose without --motion, or --frame / --sequence with it"
                )
            if (frame is None) == (sequence is None):
                raise DlaInputError("--motion", "give --frame K (one file) or --sequence FOLDER (every frame)")
        elif fps is not None:
            raise DlaInputError("--fps", "needs --motion")
        suffix = output.suffix.lower() if output is not None else f".{fmt.lower()}"
        if suffix == ".glb" and up == "z":
            raise DlaInputError(
                "--up", "glTF is +Y up by definition: a .glb is always written in glTF's axes (omit --up)"
            )

    motion_files = split_spec(motion) if motion else ()
    patterns = [f"frame_*{s}" for s in SPLAT_SUFFIXES]
    folders = [(sequence, patterns)] if sequence is not None else []
    check_outputs(files=[output], folders=folders, inputs=[avatar, checkpoint, *motion_files])
    av = read_avatar(avatar)
    mot = None
    if motion is not None:
        mot = load_motion(motion, fps=fps, phenotype=av.body.phenotype, allow_missing_joints=allow_missing_joints)
    ckpt = None if checkpoint is None else str(checkpoint)

    if rig:
        from dlacli.stages.rig import write_rigged_usd

        with naming_avatar(avatar):
            write_rigged_usd(
                av, output, motion=mot, n_gaussians=gaussians, seed=seed, where=str(avatar), checkpoint=ckpt
            )
        typer.echo(str(output))
        return

    from dlacli.stages.export import export_frames, write_gaussians

    if mot is not None and frame is not None and frame >= mot.num_frames:
        raise DlaInputError("--frame", f"frame {frame} is past the motion's last frame ({mot.num_frames - 1})")
    up = up or "y"
    if output is not None:
        frames = None if mot is None else [frame]
        with naming_avatar(avatar):
            ((_, g),) = list(export_frames(av, pose or "input", mot, frames, gaussians, seed, str(avatar), ckpt))
            write_gaussians(g, output, up)
        typer.echo(str(output))
        return
    width = max(4, len(str(mot.num_frames - 1)))
    with naming_avatar(avatar), atomic_dir(sequence) as tmp, progress_bar("exporting", mot.num_frames) as update:
        for t, g in export_frames(av, "input", mot, None, gaussians, seed, str(avatar), ckpt, progress=update):
            write_gaussians(g, Path(tmp) / f"frame_{t:0{width}d}.{fmt.lower()}", up)
    typer.echo(str(sequence))


def register(app: typer.Typer) -> None:
    app.command("export")(export)
