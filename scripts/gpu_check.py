"""One prepared GPU check (issue 22, Build 5), for when the device tool lends a CUDA machine:

  1. splat: gsplat against the CPU splatter (numba) on the same scene: image agreement (max
     abs difference, PSNR of one against the other) and forward / forward+backward medians;
  2. throughput: seconds per training step of the residual network (`dla train --method
     residual`) and of the learned method's paper preset, on the same small synthetic dataset;
  3. a short paper-preset run: its loss at the start and the end.

Writes one JSON object (stdout and OUT/gpu_check.json); numbers go to docs/train.md. With
--dry-run everything runs on the CPU at toy sizes (tiny preset, 48 px), to check the script
itself: `python scripts/gpu_check.py --dry-run --out /tmp/gpu_check`. Needs the project
installed (PYTHONPATH=src) and, for part 1 on CUDA, gsplat (`pip install 'dla[gpu]'`).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path


def _median_seconds(fn, repeats: int, sync) -> float:
    fn()  # warm-up (JIT, caches)
    sync()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def splat_check(device: str, n: int, size: int, repeats: int) -> dict:
    """gsplat (CUDA) vs the numba CPU splatter on one random scene of n Gaussians, 4 cameras."""
    import torch

    from dlacli.geometry import look_at_orbit_cameras
    from dlacli.render.splat import _gsplat_available, render_gaussians
    from dlacli.types import Gaussians

    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g) * torch.tensor([0.25, 0.15, 0.8])
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1)
    scales = torch.rand(n, 3, generator=g) * 0.01 + 0.002
    scene = Gaussians.from_rgb(means, quats, scales, torch.rand(n, generator=g), torch.rand(n, 3, generator=g))
    cams = look_at_orbit_cameras((0.0, 0.0, 0.0), 3.0, [0.0, 90.0, 180.0, 270.0], 8.0, 40.0, size)
    out = {"gaussians": n, "size": size, "cameras": 4, "gsplat": _gsplat_available()}
    cpu = render_gaussians(scene, cams)
    out["cpu_forward_s"] = _median_seconds(lambda: render_gaussians(scene, cams), repeats, lambda: None)

    def fwd_bwd(s):
        x = Gaussians(*(t.detach().clone().requires_grad_() for t in s._tensors()))
        r = render_gaussians(x, cams)
        (r.rgb.sum() + r.alpha.sum()).backward()

    out["cpu_forward_backward_s"] = _median_seconds(lambda: fwd_bwd(scene), repeats, lambda: None)
    if device == "cuda":
        sync = torch.cuda.synchronize
        gpu_scene = scene.to(torch.device("cuda"))
        gpu = render_gaussians(gpu_scene, cams)
        diff = (gpu.rgb.cpu() - cpu.rgb).abs()
        mse = float((diff**2).mean())
        out["max_abs_rgb_diff"] = float(diff.max())
        out["psnr_gpu_vs_cpu"] = 10 * torch.log10(torch.tensor(1.0 / max(mse, 1e-12))).item()
        out["max_abs_alpha_diff"] = float((gpu.alpha.cpu() - cpu.alpha).abs().max())
        out["gpu_forward_s"] = _median_seconds(lambda: render_gaussians(gpu_scene, cams), repeats, sync)
        out["gpu_forward_backward_s"] = _median_seconds(lambda: fwd_bwd(gpu_scene), repeats, sync)
    return out


def make_data(root: Path, res: int, subjects: int, novel: int) -> Path:
    from dlacli.data.dataset import DatasetSettings, synth_dataset

    if not (root / "manifest.json").is_file():
        settings = DatasetSettings(res=res, novel_views=novel, novel_poses=1, appearance="lit", wardrobe="train")
        synth_dataset(list(range(subjects)), root, settings, jobs=1)
    return root


def residual_throughput(data: Path, out: Path, steps: int, size: int, preset: str) -> dict:
    from dlacli.train.residual import ResidualTrainConfig, train_residual

    cfg = ResidualTrainConfig(
        preset=preset, steps=steps, size=size, validation=1, eval_every=10**6, checkpoint_every=10**6
    )
    rec = train_residual(data, out, cfg, log=lambda s: None)
    return _per_step(rec, "residual", preset)


def learned_run(data: Path, out: Path, steps_low: int, steps_full: int, preset: str, sizes: tuple[int, int]) -> dict:
    from dlacli.train.loop import TrainConfig, train

    cfg = TrainConfig(
        preset=preset,
        steps_low=steps_low,
        steps_full=steps_full,
        low_size=sizes[0],
        full_size=sizes[1],
        batch=1,
        targets=2,
        lr_g=1e-4,
        lr_d=1e-6,
        validation=1,
        eval_every=10**6,
        checkpoint_every=10**6,
    )
    rec = train(data, out, cfg, log=lambda s: None)
    return _per_step(rec, "learned", preset)


def _per_step(rec: dict, method: str, preset: str) -> dict:
    hist = rec["history"]
    steps = len(hist)
    totals = [h["total"] for h in hist]
    head = max(1, min(5, steps // 4))
    return {
        "method": method,
        "preset": preset,
        "steps": steps,
        "seconds": round(rec["seconds"], 2),
        "s_per_step": round(rec["seconds"] / max(steps, 1), 3),
        "loss_start": round(statistics.mean(totals[:head]), 5),
        "loss_end": round(statistics.mean(totals[-head:]), 5),
        "l1_end": round(statistics.mean(h["l1"] for h in hist[-head:]), 5),
        "validation": rec["validation"][-1] if rec["validation"] else None,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="Working folder (datasets, runs, gpu_check.json).")
    ap.add_argument("--dry-run", action="store_true", help="CPU, toy sizes: checks the script, measures nothing.")
    ap.add_argument("--paper-steps", type=int, default=200, help="Steps of the short paper-preset run (part 3).")
    args = ap.parse_args(argv)
    import torch

    dry = args.dry_run
    device = "cuda" if torch.cuda.is_available() and not dry else "cpu"
    if not dry and device != "cuda":
        print("gpu_check: no CUDA device (use --dry-run to check the script on a CPU)", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    result = {"device": torch.cuda.get_device_name(0) if device == "cuda" else "cpu", "dry_run": dry}
    t0 = time.perf_counter()
    result["splat"] = splat_check(device, 2_000 if dry else 131_072, 64 if dry else 512, 2 if dry else 10)
    print(json.dumps({"splat": result["splat"]}), flush=True)
    small = make_data(args.out / "data128", 64 if dry else 128, 3, 2)
    result["residual"] = residual_throughput(small, args.out / "run_residual", 2 if dry else 50, 48 if dry else 128,
                                             "tiny" if dry else "small")  # fmt: skip
    print(json.dumps({"residual": result["residual"]}), flush=True)
    if dry:
        result["paper_throughput"] = learned_run(small, args.out / "run_learned", 1, 1, "tiny", (32, 48))
    else:
        big = make_data(args.out / "data512", 512, 3, 2)
        result["paper_throughput"] = learned_run(big, args.out / "run_paper_speed", 5, 5, "paper", (256, 512))
        print(json.dumps({"paper_throughput": result["paper_throughput"]}), flush=True)
        n = args.paper_steps
        result["paper_run"] = learned_run(big, args.out / "run_paper", n // 2, n - n // 2, "paper", (256, 512))
    result["seconds"] = round(time.perf_counter() - t0, 1)
    text = json.dumps(result, indent=1)
    (args.out / "gpu_check.json").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
