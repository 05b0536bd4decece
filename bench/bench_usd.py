"""Benchmark: write 131,072 animated Gaussians x 30 frames to .usdc (the animate stage's output size).

Prints one JSON object: {"median_s", "size_mib", ...}. Run: python bench/bench_usd.py [--schema both]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from dlacli.io.usd import write_usd


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--instances", type=int, default=131_072)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--schema", default="instancer", choices=["instancer", "particlefield", "both"])
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    t, n = args.frames, args.instances
    positions = rng.normal(size=(t, n, 3)).astype(np.float32)  # [T, N, 3]
    quats = rng.normal(size=(t, n, 4)).astype(np.float32)  # [T, N, 4]
    quats /= np.linalg.norm(quats, axis=-1, keepdims=True)
    scales = rng.uniform(0.001, 0.02, size=(n, 3)).astype(np.float32)  # [N, 3]
    rgb = rng.uniform(size=(n, 3)).astype(np.float32)  # [N, 3]
    opacities = rng.uniform(size=n).astype(np.float32)  # [N]

    times, cpu = [], []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "anim.usdc"
        write_usd(path, positions[:1, :8], quats[:1, :8], scales[:8], rgb[:8], opacities[:8], 30.0)  # import pxr
        for _ in range(args.runs):
            start, start_cpu = time.perf_counter(), time.process_time()
            write_usd(path, positions, quats, scales, rgb, opacities, 30.0, schema=args.schema)
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
                "instances": n,
                "frames": t,
                "schema": args.schema,
            }
        )
    )


if __name__ == "__main__":
    main()
