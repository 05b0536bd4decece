"""Recognise any dla artifact (or supported third-party input) and summarise it as a JSON-able dict."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dlacli.errors import DlaInputError, excerpt
from dlacli.io.validate import npz_format


def _summarize_json(path: Path) -> dict[str, Any]:
    """A body.json, or a view folder's transforms.json (a summary of its folder)."""
    from dlacli.io.body import summarize_body
    from dlacli.io.validate import load_json
    from dlacli.io.views import summarize_views

    d = load_json(path)
    if isinstance(d, dict) and "frames" in d and "format" not in d:
        return summarize_views(path.parent)
    return summarize_body(path)


def _summarizer(path: Path) -> Callable[[Path], dict[str, Any]]:
    if path.is_dir():
        from dlacli.io.views import summarize_views

        return summarize_views
    suffix = path.suffix.lower()
    if suffix == ".json":
        return _summarize_json
    if suffix == ".ply":
        from dlacli.io.ply import summarize_ply

        return summarize_ply
    if suffix == ".spz":
        from dlacli.io.spz import summarize_spz

        return summarize_spz
    if suffix == ".splat":
        from dlacli.io.splat import summarize_splat

        return summarize_splat
    if suffix in (".usd", ".usda", ".usdc"):
        from dlacli.io.usd_read import summarize_usd

        return summarize_usd
    if suffix == ".npz":
        fmt = npz_format(path)
        if fmt.startswith("dla.motion/"):
            from dlacli.io.motion import summarize_motion

            return summarize_motion
        if fmt.startswith("dla.avatar/"):
            from dlacli.io.avatar import summarize_avatar

            return summarize_avatar
        if fmt == "amass":
            from dlacli.io.amass import summarize_amass

            return summarize_amass
        raise DlaInputError(path, f"unknown npz format {excerpt(fmt)} (expected dla.motion/1 or dla.avatar/1)")
    if suffix == ".bvh":
        from dlacli.io.bvh import summarize_bvh

        return summarize_bvh
    if suffix == ".asf":
        from dlacli.io.asf_amc import summarize_asf

        return summarize_asf
    if suffix == ".amc":
        from dlacli.io.asf_amc import summarize_amc

        return summarize_amc
    raise DlaInputError(
        path,
        "unrecognised artifact (expected a view folder, body .json, motion or avatar .npz, "
        "Gaussians .ply/.spz/.splat, .usd/.usda/.usdc, or a .bvh, .asf, .amc or AMASS .npz motion)",
    )


def summarize(path: str | os.PathLike) -> dict[str, Any]:
    """One JSON-able dict describing the artifact at `path`; always has "path" and "kind"."""
    path = Path(path)
    if not path.exists():
        raise DlaInputError(path, "no such file or folder")
    summary = _summarizer(path)(path)
    return {"path": str(path), **summary}
