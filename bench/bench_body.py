"""Benchmark the body layer on CPU: posing (1 and 30 frames) and Gaussian skinning; prints JSON.

    python bench/bench_body.py [--repeats 7] [--gaussians 131072]

Times are medians in milliseconds (after one warm-up call each).
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np
import torch


def _median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--gaussians", type=int, default=131072)
    args = parser.parse_args()

    from dlacli.body.model import get_body_model
    from dlacli.body.skinning import skin_gaussians, skin_gaussians_on_body
    from dlacli.body.uv import sample_surface, sample_uv, tangent_frames

    t0 = time.perf_counter()
    body = get_body_model()
    load_ms = (time.perf_counter() - t0) * 1e3
    rng = np.random.default_rng(0)

    def pose(t: int):
        rot = torch.from_numpy((rng.normal(size=(t, 104, 3)) * 0.2).astype(np.float32))
        return rot, torch.zeros(t, 3), torch.zeros(t, 3)

    p1, p30 = pose(1), pose(30)
    out: dict[str, object] = {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "machine": platform.processor() or platform.machine(),
        "model_load_ms": round(load_ms, 1),
    }
    with torch.no_grad():
        out["forward_1_frame_ms"] = _median_ms(lambda: body.forward({}, *p1), args.repeats)
        out["forward_30_frames_ms"] = _median_ms(lambda: body.forward({}, *p30), args.repeats)

        half = args.gaussians // 2
        f1, b1 = sample_surface(half, seed=0)
        f2, b2 = sample_uv(args.gaussians - half, seed=1)
        fid, bary = np.concatenate([f1, f2]), np.concatenate([b1, b2])
        n = fid.size
        verts = body.forward({}, *p1).vertices  # [1, V, 3]
        dxyz = torch.zeros(n, 3)
        dquat = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4)
        ds = torch.ones(n, 3)
        frames = tangent_frames(verts, fid, bary)
        out["gaussians"] = n
        out["tangent_frames_ms_per_frame"] = _median_ms(lambda: tangent_frames(verts, fid, bary), args.repeats)
        out["skin_from_frames_ms_per_frame"] = _median_ms(lambda: skin_gaussians(*frames, dxyz, dquat, ds), args.repeats)
        out["skin_from_vertices_ms_per_frame"] = _median_ms(
            lambda: skin_gaussians_on_body(verts, fid, bary, dxyz, dquat, ds), args.repeats
        )
    print(json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in out.items()}, indent=2))


if __name__ == "__main__":
    main()
