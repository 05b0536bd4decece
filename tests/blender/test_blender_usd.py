"""dla's USD files in Blender (bpy 5.0.1, run in its own Python by tests/blender/usd_probe.py):
a default import of the points schema gives coloured point clouds that move as the file says;
the oracle for every value is pxr reading the same file."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from pxr import Usd, UsdGeom

from dlacli.io.usd import write_usd

PROBE = Path(__file__).resolve().parent / "usd_probe.py"
T, N = 12, 4096  # two rigid parts' worth of Gaussians (usd_compact.GAUSSIANS_PER_PART = 2048)


def probe(bpy_python: Path, usd: Path, *args) -> dict:
    run = subprocess.run(
        [str(bpy_python), str(PROBE), str(usd), *map(str, args)], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr[-3000:]
    line = next(x for x in run.stdout.splitlines() if x.startswith("DLA-PROBE "))
    return json.loads(line[len("DLA-PROBE ") :])


def two_blobs():
    """A red blob (x < 0) that rises and a blue blob (x > 0) that turns about +Z, T frames."""
    rng = np.random.default_rng(0)
    half = N // 2
    base = np.concatenate([rng.normal([-0.4, 0, 0], 0.1, (half, 3)), rng.normal([0.4, 0, 0], 0.1, (half, 3))])
    tt = np.arange(T)[:, None]
    positions = np.repeat(base[None], T, 0)
    positions[:, :half, 2] += 0.02 * tt  # rising 2 cm a frame
    a = 0.05 * tt  # [T, 1]
    x, y = base[half:, 0] - 0.4, base[half:, 1]
    positions[:, half:, 0] = 0.4 + np.cos(a) * x - np.sin(a) * y
    positions[:, half:, 1] = np.sin(a) * x + np.cos(a) * y
    quats = np.zeros((T, N, 4), np.float32)
    quats[..., 0] = 1
    scales = np.full((N, 3), 0.02, np.float32)
    rgb = np.zeros((N, 3), np.float32)
    rgb[:half, 0], rgb[half:, 2] = 0.9, 0.9
    rgb[:, 1] = rng.uniform(0, 0.2, N)  # every point its own colour, to check the order
    return positions.astype(np.float32), quats, scales, rgb, np.ones(N, np.float32)


def pxr_points(path: Path, kind_path: str, frame: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{prim name: (world points [n, 3], colours [n, 3])} of every Points prim, from pxr."""
    stage = Usd.Stage.Open(str(path))
    out = {}
    for prim in Usd.PrimRange(stage.GetPrimAtPath(kind_path)):
        if prim.GetTypeName() != "Points":
            continue
        m = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(frame))
        local = np.asarray(prim.GetAttribute("points").Get(frame), np.float64)
        colour = np.asarray(prim.GetAttribute("primvars:displayColor").Get())
        out[prim.GetName()] = (local @ m[:3, :3] + m[3, :3], colour)
    return out


@pytest.mark.parametrize("schema, tolerance", [("points", 0.001), ("points", 0.0), ("both", 0.001)])
def test_blender_imports_coloured_moving_points(bpy_python, tmp_path, schema, tolerance):
    path = tmp_path / "blobs.usdc"
    positions, quats, scales, rgb, opacities = two_blobs()
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema=schema, tolerance=tolerance)
    frames = (0, 7)  # 7: a frame compaction may have left out (pxr and Blender interpolate)
    report = probe(bpy_python, path, "--frames", *frames, "--first", 64)
    assert report["blender"].startswith("5.")
    # Blender 5.0 sets the frame range from the stage but keeps its own fps (docs/animate.md)
    assert (report["frame_start"], report["frame_end"]) == (0, T - 1)
    assert report["fps"] == 24.0
    clouds = report["clouds"]
    want = {
        name: [pxr_points(path, "/Avatar/Points", f)[name] for f in frames]
        for name in pxr_points(path, "/Avatar/Points", 0)
    }
    assert set(clouds) == set(want) and sum(c["points"] for c in clouds.values()) == N
    for name, cloud in clouds.items():
        assert {"displayColor", "displayOpacity"} <= set(cloud["attributes"])
        colours = np.asarray(cloud["colors"])
        # Blender keeps the colours linear as float32: equal to the file's, point for point
        np.testing.assert_allclose(colours, want[name][0][1][: len(colours)], atol=1e-6)
        assert np.ptp(colours, axis=1).min() > 0.5  # red or blue, nowhere grey
        for f, (points, _) in zip(frames, want[name]):
            got = np.asarray(cloud["frames"][str(f)])
            # float32 world coordinates < 2 m through Blender's object matrix: 1e-5 m
            np.testing.assert_allclose(got, points[: len(got)], atol=1e-5)
        moved = np.linalg.norm(np.subtract(cloud["frames"]["7"], cloud["frames"]["0"]), axis=-1)
        np.testing.assert_allclose(moved, np.linalg.norm(want[name][1][0] - want[name][0][0], axis=-1)[:64], atol=1e-5)
        assert moved.min() > 0.005  # every point moves between the two frames


def test_cycles_renders_the_file_colours(bpy_python, tmp_path):
    """One tiny Cycles frame with the attribute material of docs/animate.md: the red blob on
    the left of the image, the blue one on the right (camera on -Y looking at +Y: +X is right)."""
    path, png = tmp_path / "blobs.usdc", tmp_path / "frame.png"
    write_usd(path, *two_blobs(), fps=30, schema="points", tolerance=0.001)
    probe(bpy_python, path, "--frames", 0, "--render", png, "--size", 96)
    rgb = np.asarray(Image.open(png).convert("RGB"), np.float32) / 255
    left, right = rgb[:, :48].reshape(-1, 3), rgb[:, 48:].reshape(-1, 3)
    # the points: saturated pixels (the dark grey background has max - min ~ 0)
    lit_left, lit_right = left[np.ptp(left, 1) > 0.15], right[np.ptp(right, 1) > 0.15]
    assert len(lit_left) > 50 and len(lit_right) > 50
    assert lit_left[:, 0].mean() > 2 * lit_left[:, 2].mean()
    assert lit_right[:, 2].mean() > 2 * lit_right[:, 0].mean()
