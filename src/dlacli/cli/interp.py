"""`dla interp`: blend two avatars by interpolating their latent codes Z."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli import options
from dlacli.cli.options import check_suffix


def interp(
    a: Path = options.avatar("Avatar at t = 0 (avatar.npz).", metavar="A"),
    b: Path = options.avatar("Avatar at t = 1 (avatar.npz).", metavar="B"),
    output: Path = options.output("avatar.npz to write, or a folder with --steps."),
    t: float = typer.Option(
        0.5,
        "--t",
        min=-10.0,
        max=10.0,
        callback=options.finite,
        help="Blend fraction: 0 gives A exactly, 1 gives B exactly.",
    ),
    steps: int = typer.Option(
        0,
        "--steps",
        min=0,
        max=1000,
        help="Write this many avatars from t=0 to t=1 (inclusive) into the folder OUTPUT instead.",
    ),
    video: Optional[Path] = options.side_output(
        "--video", "With --steps: also render the blend from the front as an .mp4.", (".mp4",), "video"
    ),
    size: int = options.image_size(512, "Video size in pixels (square)."),
    fps: float = options.video_fps(12.0, "Frame rate of --video."),
) -> None:
    """Blend avatars A and B: z = (1 - t) z_A + t z_B; the body blends too."""
    import numpy as np

    from dlacli.cli.progress import progress_bar
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import atomic_dir, check_outputs, output_group
    from dlacli.io.avatar import read_avatar, write_avatar
    from dlacli.stages.edit import interpolate

    if steps == 0:
        if video is not None:
            raise DlaInputError("--video", "needs --steps (a video of one blend would be a still)")
        check_suffix(output, (".npz",), "avatar", " (or --steps K for a folder)")
        check_outputs(files=[output], inputs=[a, b])
        avatar_a, avatar_b = read_avatar(a), read_avatar(b)
        write_avatar(interpolate(avatar_a, avatar_b, t, str(a), str(b)), output)
        typer.echo(str(output))
        return
    if steps < 2:
        raise DlaInputError("--steps", f"needs at least 2 avatars (t = 0 and t = 1), got {steps}")
    check_outputs(files=[video], folders=[(output, ("interp_*.npz",))], inputs=[a, b])
    avatar_a, avatar_b = read_avatar(a), read_avatar(b)
    if video is not None:
        from dlacli.io.video import write_video
        from dlacli.stages.render import render_avatar, turntable_cameras

        camera = turntable_cameras(avatar_a, 1, size)  # one fixed front camera for every blend
    frames = []  # uint8 video frames only: each blend is written, rendered and dropped in turn
    with output_group(), atomic_dir(output) as tmp, progress_bar("blending", steps) as update:
        for k in range(steps):
            avatar = interpolate(avatar_a, avatar_b, k / (steps - 1), str(a), str(b))
            write_avatar(avatar, tmp / f"interp_{k:03d}.npz")
            if video is not None:
                rgba = next(render_avatar(avatar, camera, [None], where=str(a))).rgba
                frames.append((np.clip(rgba, 0, 1) * 255 + 0.5).astype(np.uint8))
            update(k + 1)
        if video is not None:
            write_video(frames, video, fps)
    typer.echo(str(output))


def register(app: typer.Typer) -> None:
    app.command("interp")(interp)
