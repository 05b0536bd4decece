"""`dla body ...`: the body model's UV regions."""

from __future__ import annotations

from pathlib import Path

import typer

from dlacli.cli import options

body_app = typer.Typer(
    name="body",
    help="The body model (anny): UV regions.",
    no_args_is_help=True,
    add_completion=False,
)

# one colour per part (dlacli.body.regions.PARTS), distinct and readable on a dark background
_PART_COLORS = {
    "face": (255, 196, 140),
    "hair": (140, 90, 40),
    "torso": (90, 140, 230),
    "left_arm": (60, 200, 90),
    "right_arm": (230, 70, 70),
    "left_hand": (160, 255, 150),
    "right_hand": (255, 160, 170),
    "left_leg": (40, 150, 150),
    "right_leg": (200, 90, 200),
    "left_foot": (150, 240, 240),
    "right_foot": (245, 190, 250),
}


def draw_regions(resolution: int):
    """A PIL image: the UV layout coloured by part, upper/lower body boundary, and a legend."""
    import numpy as np
    from PIL import Image, ImageDraw, ImageFont

    from dlacli.body.regions import PARTS, part_map, region_mask

    pm = part_map(resolution)
    rgb = np.full((resolution, resolution, 3), 24, dtype=np.uint8)
    for i, name in enumerate(PARTS):
        rgb[pm == i] = _PART_COLORS[name]
    # darken the lower body a little so the upper/lower split is visible
    lower = region_mask("lower_body", resolution)
    rgb[lower] = (rgb[lower].astype(np.float32) * 0.7).astype(np.uint8)

    font_size = max(12, resolution // 36)
    try:
        font = ImageFont.load_default(size=font_size)
    except TypeError:  # Pillow < 10.1
        font = ImageFont.load_default()
    rows = [(name.replace("_", " "), _PART_COLORS[name]) for name in PARTS]
    line = int(font_size * 1.6)
    legend_w = max(220, font_size * 14)
    canvas = Image.new("RGB", (resolution + legend_w, max(resolution, line * (len(rows) + 6))), (24, 24, 24))
    canvas.paste(Image.fromarray(rgb), (0, 0))
    draw = ImageDraw.Draw(canvas)
    x0 = resolution + font_size
    y = font_size
    draw.text((x0, y), "UV regions (anny)", fill=(255, 255, 255), font=font)
    y += int(line * 1.4)
    for label, color in rows:
        draw.rectangle([x0, y, x0 + font_size, y + font_size], fill=color)
        draw.text((x0 + int(font_size * 1.6), y - 2), label, fill=(235, 235, 235), font=font)
        y += line
    y += line // 2
    for text in ("left = person's left (+X)", "darker: lower body", "head = face + hair"):
        draw.text((x0, y), text, fill=(200, 200, 200), font=font)
        y += line
    return canvas


def regions(
    output: Path = options.output("PNG file to write.", (".png",), "image"),
    res: int = options.image_size(512, "UV map resolution in texels.", "--res"),
) -> None:
    """Draw the named UV regions (face, hair, hands, feet, arms, legs, torso, ...) with a legend."""
    from dlacli.io.atomic import atomic_path, check_outputs

    check_outputs(files=[output])
    image = draw_regions(res)
    with atomic_path(output) as tmp:
        image.save(tmp, format="PNG")
    typer.echo(str(output))


body_app.command("regions")(regions)


def register(app: typer.Typer) -> None:
    app.add_typer(body_app, name="body")
