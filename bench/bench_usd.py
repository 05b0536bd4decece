"""Benchmark: write 131,072 animated Gaussians x 30 frames as .usdc (the animate stage's output):
time and size per schema, every frame exactly (tolerance 0) and compact (tolerance in mm).

The motion is synthetic and smooth, like a walk: 16 "limbs" swing about their own pivots
(+-30 degrees, 1 Hz, each its own phase) while the whole body moves forward at 1.3 m/s and bobs
2 cm at 2 Hz; random per-frame positions would be a worst case no compaction helps.

Prints one JSON object per tolerance. Run: python bench/bench_usd.py [--schema points] [--tolerance 0 1]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from dlacli.io.usd import SCHEMAS, write_usd

LIMBS = 16


def walk_like(t: int, n: int, fps: float = 30.0, seed: int = 0):
    """positions [T, N, 3], quats [T, N, 4] (w, x, y, z), scales [N, 3], rgb [N, 3], opacities [N]."""
    rng = np.random.default_rng(seed)
    limb = rng.integers(0, LIMBS, n)
    pivot = rng.uniform([-0.3, -0.1, -0.9], [0.3, 0.1, 0.6], (LIMBS, 3))
    base = pivot[limb] + rng.normal(0, 0.08, (n, 3))  # [N, 3]
    phase = rng.uniform(0, 2 * np.pi, LIMBS)
    secs = np.arange(t) / fps
    angle = np.radians(30) * np.sin(2 * np.pi * secs[:, None] + phase)  # [T, LIMBS] about +X
    c, s = np.cos(angle)[:, limb], np.sin(angle)[:, limb]  # [T, N]
    rel = base - pivot[limb]
    positions = np.stack([np.broadcast_to(rel[:, 0], c.shape), c * rel[:, 1] - s * rel[:, 2], s * rel[:, 1] + c * rel[:, 2]], -1)
    positions += pivot[limb]
    positions[..., 1] -= 1.3 * secs[:, None]  # walking towards -Y
    positions[..., 2] += 0.02 * np.sin(4 * np.pi * secs)[:, None]
    quats = np.stack([np.cos(angle / 2)[:, limb], np.sin(angle / 2)[:, limb], np.zeros_like(c), np.zeros_like(c)], -1)
    scales = rng.uniform(0.001, 0.005, size=(n, 3))
    rgb, opacities = rng.uniform(size=(n, 3)), rng.uniform(0.5, 1, size=n)
    return [a.astype(np.float32) for a in (positions, quats, scales, rgb, opacities)]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--instances", type=int, default=131_072)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--schema", default="instancer", choices=SCHEMAS)
    parser.add_argument("--tolerance", type=float, nargs="+", default=[0.0, 1.0], help="millimetres; 0 = exact")
    args = parser.parse_args()

    positions, quats, scales, rgb, opacities = walk_like(args.frames, args.instances)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "anim.usdc"
        write_usd(path, positions[:1, :8], quats[:1, :8], scales[:8], rgb[:8], opacities[:8], 30.0)  # import pxr
        for tol in args.tolerance:
            times, cpu = [], []
            for _ in range(args.runs):
                start, start_cpu = time.perf_counter(), time.process_time()
                write_usd(path, positions, quats, scales, rgb, opacities, 30.0, schema=args.schema, tolerance=tol / 1000)
                times.append(time.perf_counter() - start)
                cpu.append(time.process_time() - start_cpu)
            size = path.stat().st_size
            print(
                json.dumps(
                    {
                        "median_s": round(statistics.median(times), 3),
                        "size_mib": round(size / 2**20, 2),
                        "runs_s": [round(x, 3) for x in times],
                        "cpu_median_s": round(statistics.median(cpu), 3),  # process CPU time, all threads
                        "instances": args.instances,
                        "frames": args.frames,
                        "schema": args.schema,
                        "tolerance_mm": tol,
                    }
                ),
                flush=True,
            )


if __name__ == "__main__":
    main()
