"""Benchmark of Gaussian splatting on the CPU: the numba tile kernel vs the dense pure-torch path.

Prints one JSON object on stdout. Every measurement runs in a fresh subprocess, so that
- `first_call_ms` is the first forward of a new process (numba loads its on-disk cache; with
  `--cold` one extra run uses an empty NUMBA_CACHE_DIR to measure the JIT compile itself), and
- `peak_mb` is the transient memory of one forward + backward after warm-up: the peak resident
  set sampled every 0.5 ms by a thread (/proc/self/statm) minus the resident set before the call
  (autograd graph, kernel buffers, numpy/torch temporaries); `maxrss_growth_mb` is the growth of
  the process's peak resident set (getrusage ru_maxrss) from just after the scene is built to the
  end of all calls, so it also counts loading the compiled kernels on the first call.
Times are medians (and minima, `*_min_ms`, less sensitive to other load on the machine; the 1-min
load average is recorded) over `--repeats` calls after one warm-up call; "fwd" runs under no_grad,
"fwd_bwd" is a forward with gradients plus backward of rgb.sum() + alpha.sum() + depth.sum().

Scene: N random Gaussians in a 0.5 x 0.3 x 1.8 m box (a standing person) seen from 3 m with a
50 degree field of view, scales log-uniform in [0.3, 3] cm, opacities uniform in [0.1, 1], random
rotations and SH colours. The "torch" path is dlacli.render.splat_reference.reference_render in
the tile-free pure-torch `pairs_render` (dlacli.render.splat_reference): it builds the list of
(Gaussian, pixel) pairs that can count, sorts them by (pixel, depth) and composites with a segmented
cumulative sum; autograd does the backward. Same float32 inputs, same images (to float precision).
The "dense" path (reference_render in float32, chunked over pixels, O(pixels x N)) runs only on
the small calibration case.

    python bench/bench_splat.py            # full table
    python bench/bench_splat.py --quick    # smoke run

Before / after a change to the kernels, in the same run: `--baseline DIR` also runs every numba
case with another copy of the package first on PYTHONPATH (path "numba_baseline", right after
the "numba" case) and reports the ratios current / baseline (`vs_baseline`); `--rounds R`
alternates the two R times per case (the ratios are then medians over the rounds, which cancels
slow drifts of the machine's load); `--no-torch` skips the slow torch and dense paths. E.g.

    git archive HEAD src | tar -x -C /tmp/base
    python bench/bench_splat.py --baseline /tmp/base/src --no-torch --rounds 3
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time

# Before torch is imported: passive OpenMP waiting for torch's pool too (see splat_kernels.py).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

FULL = [(20_000, 256), (20_000, 512), (65_536, 256), (65_536, 512), (131_072, 256), (131_072, 512)]
CALIBRATION = [(2_048, 128)]  # small enough for the dense torch path, to compare both directly
QUICK = [(2_048, 128), (20_000, 256)]


def make_scene(n: int, res: int, sh_degree: int, seed: int = 0):
    import numpy as np
    import torch

    from dlacli.types import Cameras, Gaussians

    g = torch.Generator().manual_seed(seed)
    box = torch.tensor([0.5, 0.3, 1.8])
    means = (torch.rand(n, 3, generator=g) - 0.5) * box
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(0.003), math.log(0.03), generator=g))
    opac = torch.empty(n).uniform_(0.1, 1.0, generator=g)
    sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g) * 0.3
    gaussians = Gaussians(means, quats, scales, opac, sh)
    f = 0.5 * res / math.tan(math.radians(25.0))
    c2w = np.eye(4)  # OpenGL axes: camera +X = world +X, +Y = world +Z, looks along world +Y
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = [1, 0, 0], [0, 0, 1], [0, -1, 0], [0, -3, 0]
    cams = Cameras.from_c2w_opengl(c2w[None], f, f, res / 2, res / 2, res, res)
    return gaussians, cams


def _median_min_ms(fn, repeats: int) -> tuple[float, float]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    times.sort()
    return round(times[len(times) // 2], 1), round(times[0], 1)


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _peak_rss_growth_mb(fn) -> float | None:
    """Peak of the resident set while `fn` runs, minus the resident set before (sampled every
    0.5 ms by a thread; Linux only)."""
    import threading

    if not os.path.exists("/proc/self/statm"):
        return None
    base = _rss_bytes()
    peak = [base]
    stop = threading.Event()

    def poll():
        while not stop.is_set():
            peak[0] = max(peak[0], _rss_bytes())
            time.sleep(0.0005)

    th = threading.Thread(target=poll, daemon=True)
    th.start()
    fn()
    stop.set()
    th.join()
    peak[0] = max(peak[0], _rss_bytes())
    return round((peak[0] - base) / 2**20, 1)


def worker(path: str, n: int, res: int, repeats: int, sh_degree: int, budget_s: float,
           mem_budget_gb: float) -> dict:
    import torch

    from dlacli.render.splat import render_gaussians
    from dlacli.render.splat_reference import pairs_render, reference_render

    g, cams = make_scene(n, res, sh_degree)
    params = [g.means, g.quats, g.scales, g.opacities, g.sh]
    for p in params:
        p.requires_grad_(True)
    rec = {"path": path, "n": n, "res": res, "sh_degree": sh_degree,
           "threads": torch.get_num_threads(), "loadavg_1min": round(os.getloadavg()[0], 2)}
    import dlacli.render.splat as splat_module

    rec["module"] = splat_module.__file__
    if path in ("numba", "numba_baseline"):
        render = render_gaussians
    elif path == "torch":
        render = pairs_render
    else:
        chunk = max(1, min(res * res, int(2e7 // max(n, 1))))  # ~20M pairs per dense block
        rec["chunk_pixels"] = chunk

        def render(gs, cs):
            return reference_render(gs, cs, chunk=chunk)

        # extrapolate from one chunk before committing to the whole image
        sub = type(cams)(cams.viewmats, cams.Ks, res, max(1, chunk // res))
        t0 = time.perf_counter()
        with torch.no_grad():
            render(g, sub)
        est = (time.perf_counter() - t0) * (res * res) / (sub.width * sub.height)
        est_mem_gb = n * res * res * 4 * 12 / 1e9  # ~12 float32 [P, N] tensors kept for backward
        rec["est_fwd_s"] = round(est, 2)
        rec["est_bwd_mem_gb"] = round(est_mem_gb, 1)
        if est * (2 + 2 * repeats) > budget_s:
            rec["skipped"] = (f"dense O(pixels x N): about {est:.1f} s per forward, extrapolated "
                              f"from {sub.width}x{sub.height} pixels; over the {budget_s:.0f} s budget")
            return rec
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    with torch.no_grad():
        out = render(g, cams)
    first = time.perf_counter() - t0
    rec["first_call_ms"] = round(first * 1e3, 1)
    rec["coverage"] = round(float((out.alpha > 0.5).float().mean()), 4)
    if not path.startswith("numba") and first * 4 * (1 + repeats) > budget_s:
        rec["skipped"] = f"first forward took {first:.1f} s; timed runs would exceed {budget_s:.0f} s"
        return rec

    def fwd():
        with torch.no_grad():
            render(g, cams)

    def fwd_bwd():
        o = render(g, cams)
        (o.rgb.sum() + o.alpha.sum() + o.depth.sum()).backward()
        for p in params:
            p.grad = None

    fwd()
    rec["fwd_ms"], rec["fwd_min_ms"] = _median_min_ms(fwd, repeats)
    if path != "dense" or n * res * res * 4 * 12 / 1e9 <= mem_budget_gb:
        t0 = time.perf_counter()
        fwd_bwd()
        rec["first_fwd_bwd_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
        rec["fwd_bwd_ms"], rec["fwd_bwd_min_ms"] = _median_min_ms(fwd_bwd, repeats)
        rec["peak_mb"] = _peak_rss_growth_mb(fwd_bwd)
    else:
        rec["fwd_bwd_skipped"] = f"autograd graph would hold about {est_mem_gb:.0f} GB"
    rec["maxrss_growth_mb"] = round(
        (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024, 1)
    return rec


def run_sub(args_list: list[str], env=None) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", *args_list]
    # big blocks straight from / back to the OS, so that the sampled resident set follows
    # allocations and frees (glibc otherwise keeps freed blocks after raising its threshold)
    env = dict(os.environ if env is None else env, MALLOC_MMAP_THRESHOLD_="131072")
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        return {"error": res.stderr.strip().splitlines()[-1:] or ["failed"], "args": args_list}
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small smoke run")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--sh-degree", type=int, default=0)
    ap.add_argument("--budget-s", type=float, default=150.0, help="time budget per torch case")
    ap.add_argument("--mem-budget-gb", type=float, default=6.0, help="torch backward memory cap")
    ap.add_argument("--cold", action="store_true", help="also time a JIT compile with no cache")
    ap.add_argument("--baseline", metavar="DIR", help="also run the numba cases with the dlacli "
                    "package under DIR (a src folder) first on PYTHONPATH, and report the ratios")
    ap.add_argument("--rounds", type=int, default=1, help="with --baseline: alternate the two "
                    "versions this many times per case; ratios are medians over the rounds")
    ap.add_argument("--no-torch", action="store_true", help="skip the torch and dense paths")
    ap.add_argument("--worker", nargs=3, metavar=("PATH", "N", "RES"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        path, n, res = a.worker[0], int(a.worker[1]), int(a.worker[2])
        rec = worker(path, n, res, a.repeats, a.sh_degree, a.budget_s, a.mem_budget_gb)
        print(json.dumps(rec))
        return
    cases = QUICK if a.quick else CALIBRATION + FULL
    repeats = max(1, a.repeats if not a.quick else min(a.repeats, 3))
    common = ["--repeats", str(repeats), "--sh-degree", str(a.sh_degree),
              "--budget-s", str(a.budget_s), "--mem-budget-gb", str(a.mem_budget_gb)]
    report = {"cpu_count": os.cpu_count(), "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
              "loadavg_start": os.getloadavg(), "results": []}
    if a.cold:
        with tempfile.TemporaryDirectory() as tmp:
            env = dict(os.environ, NUMBA_CACHE_DIR=tmp)
            rec = run_sub(["numba", "2048", "64", "--repeats", "1"], env=env)
            report["cold_jit_ms"] = {k: rec.get(k) for k in ("first_call_ms", "first_fwd_bwd_ms")}
    base_env = None
    if a.baseline:
        base_dir = os.path.abspath(a.baseline)
        base_env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            [base_dir] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
        report["baseline"] = base_dir
        report["vs_baseline"] = []
    for n, res in cases:
        dense = ("dense",) if (n, res) in CALIBRATION and not a.quick else ()
        paths = ("numba",) if a.no_torch else ("numba", "torch") + dense
        for path in paths:
            if path != "numba" or base_env is None:
                rec = run_sub([path, str(n), str(res), *common])
                report["results"].append(rec)
                print(json.dumps(rec), file=sys.stderr, flush=True)
                continue
            ratios: dict[str, list[float]] = {}
            for r in range(max(1, a.rounds)):
                pair = {}
                order = ("numba", "numba_baseline") if r % 2 == 0 else ("numba_baseline", "numba")
                for which in order:
                    rec = run_sub([which, str(n), str(res), *common],
                                  env=base_env if which == "numba_baseline" else None)
                    rec["round"] = r
                    report["results"].append(rec)
                    print(json.dumps(rec), file=sys.stderr, flush=True)
                    pair[which] = rec
                for key in ("fwd_ms", "fwd_bwd_ms", "fwd_min_ms", "fwd_bwd_min_ms", "peak_mb"):
                    cur, base = pair["numba"].get(key), pair["numba_baseline"].get(key)
                    if cur and base:
                        ratios.setdefault(key, []).append(cur / base)
            ratio = {"n": n, "res": res, "rounds": max(1, a.rounds)}
            for key, vals in ratios.items():
                ratio[key] = round(sorted(vals)[len(vals) // 2], 3)
            report["vs_baseline"].append(ratio)
    report["loadavg_end"] = os.getloadavg()
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
