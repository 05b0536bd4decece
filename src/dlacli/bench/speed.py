"""Speed suites (`dla bench speed`): medians of what each part of the toolkit costs, as "speed" rows.

Suites (SUITES):
- startup: `dla --version` and `dla info <body.json>`, each a fresh interpreter, and whether
  torch got imported;
- splat: render_gaussians forward (no_grad) and forward + backward of rgb + alpha + depth sums,
  per Gaussian count and image size, each case in a fresh process (its first forward includes
  loading numba's cache; peak_mb is the resident-set growth of one forward + backward, sampled
  every 0.5 ms). Paths: "numba" (the CPU kernels), "torch" (the pure-torch pairs renderer of
  dlacli.render.splat_reference, autograd backward), "dense" (reference_render, O(pixels x N),
  small cases only), "gsplat" (CUDA only; skipped with a note otherwise), and with `baseline` a
  second copy of the package ("numba_baseline", alternated with "numba" for `rounds` rounds);
  with `cold`, one first call with an empty numba cache (the JIT compile itself).
  The scene: N random Gaussians in a 0.5 x 0.3 x 1.8 m box seen from 3 m (50 degree field of
  view), scales log-uniform in [3, 30] mm, opacities uniform in [0.1, 1], random rotations and
  SH colours;
- body: the body model's first build in this process, posing 1 and 30 frames, tangent frames,
  skinning, and pose + skin per frame (what animate does per frame);
- lift: synth of one subject, and lift at each number of refinement steps;
- animate: pose_avatar of a walk (per frame) and its USD write (animate's defaults);
- usd: write_usd throughput on a synthetic walk-like motion, per schema and tolerance;
- render: frames per second of an animated avatar (animate's preview renderer) and turntable
  images of its own pose;
- view: the `dla view` page of a walk in headless Chromium (software WebGL2 through SwiftShader):
  the page's own timing of successive frames (frames per second, and per frame the JS part,
  skinning the centres + the depth sort, and the GL part); skipped with a note without Chromium;
- dream: the whole `dla dream` command on the bundled sample photo (with detection, and with its
  stored keypoints), each run a fresh interpreter as a user runs it, and its stages in this
  process: detection, the body fit, framing + the views of the body and the shell backends,
  plausibility, and writing the folder (with the fit overlay); first_seconds is a stage's first
  call in this process (detection: importing mediapipe; fit: building the body model);
- motion: `dla motion from-video` on a synthetic video of the built-in walk (data/video.py; 10 s at
  30 fps, 320 px): the whole command in a fresh interpreter (rows carry the frame count as
  `items`, so video frames per second = items / seconds), and in this process its detection, its
  fit and the process's CPU seconds.
Times are medians over `repeats` calls after one warm-up call, unless a row says repeats = 1
(stages too slow to repeat). Speed is measured here, never asserted in tests.
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from dlacli.bench.speed_config import DENSE_MAX_PAIRS, SUITES, SpeedConfig, cli_seconds, median_min, run_isolated
from dlacli.bench.speed_stages import (
    animate_suite,
    dream_suite,
    lift_suite,
    motion_suite,
    render_suite,
    usd_suite,
    view_suite,
)

# ------------------------------------------------------------------------------------ startup


def _startup(cfg: SpeedConfig, row) -> list[dict]:
    from dlacli.io.body import write_body
    from dlacli.types import BodyParams

    tmp = tempfile.mkdtemp(prefix="dla-startup-")
    body = Path(tmp) / "body.json"
    write_body(BodyParams(pose={"neck01": [0.1, 0.0, 0.0]}), body)
    commands = {"version": ["--version"], "info_body_json": ["info", str(body)]}
    out = []
    cli_seconds(["--version"])  # warm the file-system cache and the .pyc files
    for case, argv in commands.items():
        runs = [cli_seconds(argv) for _ in range(max(1, cfg.startup_runs))]
        times = [t for t, _ in runs]
        out.append(
            row(
                "startup",
                case,
                "cli",
                {},
                statistics.median(times),
                len(times),
                min_seconds=min(times),
                torch_loaded=any(loaded for _, loaded in runs),
            )
        )
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)
    return out


# ------------------------------------------------------------------------------------ splat
# median_min, _splat_scene and _splat_case run in a fresh interpreter (their source is sent with `python -c`),
# so that a baseline copy of the package can be measured the same way: they import only
# dlacli.types and dlacli.render, whose APIs the baseline shares.


def _splat_scene(n: int, res: int, sh_degree: int, seed: int = 0):
    import math

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
    f = 0.5 * res / math.tan(math.radians(25.0))
    c2w = np.eye(4)  # OpenGL axes: camera +X = world +X, +Y = world +Z, looks along world +Y
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = [1, 0, 0], [0, 0, 1], [0, -1, 0], [0, -3, 0]
    return Gaussians(means, quats, scales, opac, sh), Cameras.from_c2w_opengl(
        c2w[None], f, f, res / 2, res / 2, res, res
    )


def _splat_case(path: str, n: int, res: int, repeats: int, sh_degree: int, budget_s: float) -> dict:
    import os
    import threading
    import time

    import torch

    from dlacli.render.splat import render_gaussians

    g, cams = _splat_scene(n, res, sh_degree)  # noqa: F821 - sent along with this function
    cuda = path == "gsplat"
    if cuda:
        g, cams = g.to("cuda"), cams.to("cuda")
    params = [g.means, g.quats, g.scales, g.opacities, g.sh]
    for p in params:
        p.requires_grad_(True)
    rec = {"threads": torch.get_num_threads(), "loadavg_1min": round(os.getloadavg()[0], 2)}
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    if path == "torch":
        from dlacli.render.splat_reference import pairs_render as render
    elif path == "dense":
        from dlacli.render.splat_reference import reference_render

        def render(gs, cs):
            return reference_render(gs, cs, chunk=max(1, min(res * res, int(2e7 // max(n, 1)))))
    else:
        render = render_gaussians

    def fwd():
        with torch.no_grad():
            return render(g, cams)

    def fwd_bwd():
        o = render(g, cams)
        (o.rgb.sum() + o.alpha.sum() + o.depth.sum()).backward()
        for p in params:
            p.grad = None

    t0 = time.perf_counter()
    out = fwd()
    sync()
    rec["first_seconds"] = time.perf_counter() - t0
    rec["coverage"] = float((out.alpha > 0.5).float().mean())
    if path in ("torch", "dense") and rec["first_seconds"] * 4 * (1 + repeats) > budget_s:
        rec["skipped"] = (
            f"first forward took {rec['first_seconds']:.1f} s; its runs would pass the {budget_s:.0f} s budget"
        )
        return rec
    rec["fwd"] = median_min(fwd, repeats, sync)  # (one more warm-up call, then the timed ones)
    rec["fwd_bwd"] = median_min(fwd_bwd, repeats, sync)
    if cuda:
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
        fwd_bwd()
        sync()
        rec["peak_mb"] = (torch.cuda.max_memory_allocated() - base) / 2**20
    elif os.path.exists("/proc/self/statm"):
        page = os.sysconf("SC_PAGE_SIZE")

        def rss():
            with open("/proc/self/statm") as f:
                return int(f.read().split()[1]) * page

        base, peak, stop = rss(), [0], threading.Event()

        def poll():
            while not stop.is_set():
                peak[0] = max(peak[0], rss())
                time.sleep(0.0005)

        th = threading.Thread(target=poll, daemon=True)
        th.start()
        fwd_bwd()
        stop.set()
        th.join()
        rec["peak_mb"] = (max(peak[0], rss()) - base) / 2**20
    return rec


def _run_splat_case(
    path: str, n: int, res: int, cfg: SpeedConfig, pythonpath: str | None = None, numba_cache: str | None = None
) -> dict:
    args = [path if path != "numba_baseline" else "numba", n, res, cfg.repeats, cfg.sh_degree, cfg.torch_budget_s]
    return run_isolated((_splat_scene, _splat_case), args, pythonpath, numba_cache, sampled_rss=True)


def _gsplat_note() -> str | None:
    """None when gsplat can run here, else why not."""
    import importlib.util

    import torch

    if not torch.cuda.is_available():
        return "no CUDA device"
    if importlib.util.find_spec("gsplat") is None:
        return "gsplat is not installed (extra 'gpu')"
    return None


def _splat(cfg: SpeedConfig, row, log) -> list[dict]:
    paths = list(cfg.splat_paths)
    note = _gsplat_note()
    if note is None and "gsplat" not in paths:
        paths.append("gsplat")
    out = []
    if note is not None:
        log(f"splat: gsplat skipped ({note})")
        out.append(row("splat", "fwd", "gsplat", {}, None, 0, skipped=note))
    if cfg.cold:
        with tempfile.TemporaryDirectory() as cache:
            rec = _run_splat_case("numba", 2_048, 64, replace(cfg, repeats=1), numba_cache=cache)
        if "first_seconds" in rec:
            out.append(row("splat", "cold_first_call", "numba", {"n": 2_048, "res": 64}, rec["first_seconds"], 1))
            log(f"splat: first call with an empty numba cache {rec['first_seconds']:.1f} s")
    for n, res in cfg.splat_cases:
        case_cfg = {"n": n, "res": res, "sh_degree": cfg.sh_degree}
        todo = []
        for path in paths:
            if path == "dense" and n * res * res > DENSE_MAX_PAIRS:
                continue
            if path == "numba" and cfg.baseline:
                for r in range(max(1, cfg.rounds)):
                    todo += (
                        [("numba", r), ("numba_baseline", r)] if r % 2 == 0 else [("numba_baseline", r), ("numba", r)]
                    )
            else:
                todo.append((path, 0))
        for path, rnd in todo:
            rec = _run_splat_case(path, n, res, cfg, cfg.baseline if path == "numba_baseline" else None)
            c = {**case_cfg, **({"round": rnd} if cfg.baseline and path.startswith("numba") else {})}
            if "skipped" in rec and "fwd" not in rec:
                out.append(
                    row(
                        "splat", "fwd", path, c, None, 0, skipped=rec["skipped"], first_seconds=rec.get("first_seconds")
                    )
                )
                log(f"splat {path} n={n} res={res}: skipped ({rec['skipped']})")
                continue
            out.append(
                row(
                    "splat",
                    "fwd",
                    path,
                    c,
                    rec["fwd"][0],
                    cfg.repeats,
                    min_seconds=rec["fwd"][1],
                    first_seconds=rec["first_seconds"],
                )
            )
            out.append(
                row(
                    "splat",
                    "fwd_bwd",
                    path,
                    c,
                    rec["fwd_bwd"][0],
                    cfg.repeats,
                    min_seconds=rec["fwd_bwd"][1],
                    peak_mb=rec.get("peak_mb"),
                )
            )
            log(
                f"splat {path} n={n} res={res}: fwd {rec['fwd'][0] * 1e3:.1f} ms, fwd+bwd "
                f"{rec['fwd_bwd'][0] * 1e3:.1f} ms"
            )
    return out


# ------------------------------------------------------------------------------------ body


def _body(cfg: SpeedConfig, row, log) -> list[dict]:
    import numpy as np
    import torch

    from dlacli.avatar import gaussian_map as gm
    from dlacli.body.model import get_body_model
    from dlacli.body.skinning import skin_gaussians
    from dlacli.body.uv import tangent_frames

    t0 = time.perf_counter()
    body = get_body_model()
    out = [row("body", "model_build", "cpu", {}, time.perf_counter() - t0, 1)]
    rng = np.random.default_rng(0)

    def pose(t: int):
        rot = torch.from_numpy((rng.normal(size=(t, body.num_bones, 3)) * 0.2).astype(np.float32))
        return rot, torch.zeros(t, 3), torch.zeros(t, 3)

    n = cfg.gaussians
    samples = gm.make_samples(n, 0)
    fmap = torch.zeros(gm.CHANNELS, 64, 64)
    fmap[7] = 1.0
    with torch.no_grad():
        for t in (1, 30):
            p = pose(t)
            med, lo = median_min(lambda p=p: body.forward({}, *p), cfg.repeats)
            out.append(row("body", "forward", "cpu", {"frames": t}, med, cfg.repeats, min_seconds=lo, items=t))
        p1 = pose(1)
        verts = body.forward({}, *p1).vertices
        frames = tangent_frames(verts, samples.face_id, samples.bary)
        zeros, ones = torch.zeros(n, 3), torch.ones(n, 3)
        dquat = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4)
        cases = {
            "tangent_frames": lambda: tangent_frames(verts, samples.face_id, samples.bary),
            "skin": lambda: skin_gaussians(*frames, zeros, dquat, ones),
            "pose_and_skin": lambda: gm.skinned_params(
                fmap, samples, gm.sample_frames(body.forward({}, *p1).vertices, samples)
            ),
        }
        for case, fn in cases.items():
            med, lo = median_min(fn, cfg.repeats)
            out.append(row("body", case, "cpu", {"gaussians": n}, med, cfg.repeats, min_seconds=lo, items=1))
            log(f"body {case} ({n} Gaussians): {med * 1e3:.1f} ms per frame")
    return out


# ------------------------------------------------------------------------------------ driver


def run(
    suites: list[str] | tuple[str, ...] = SUITES, cfg: SpeedConfig | None = None, log: Callable[[str], None] = print
) -> list[dict]:
    """The suites' speed rows (dlacli.bench.rows "speed"), one `run` id for all."""
    from dlacli.bench.rows import default_device, speed_row

    cfg = cfg or SpeedConfig()
    unknown = [s for s in suites if s not in SUITES]
    if unknown:
        from dlacli.errors import DlaInputError

        raise DlaInputError("--suite", f"unknown suite {unknown[0]!r} (one of {', '.join(SUITES)})")
    run_id = time.strftime("%Y%m%dT%H%M%S") + f"-{os.getpid()}"
    device = default_device()

    def row(suite, case, method, config, seconds, repeats, **optional):
        return speed_row(suite, case, method, config, seconds, repeats, run_id, device, **optional)

    fns = {
        "startup": lambda: _startup(cfg, row),
        "splat": lambda: _splat(cfg, row, log),
        "body": lambda: _body(cfg, row, log),
        "lift": lambda: lift_suite(cfg, row, log),
        "animate": lambda: animate_suite(cfg, row, log),
        "usd": lambda: usd_suite(cfg, row, log),
        "render": lambda: render_suite(cfg, row, log),
        "view": lambda: view_suite(cfg, row, log),
        "dream": lambda: dream_suite(cfg, row, log),
        "motion": lambda: motion_suite(cfg, row, log),
    }
    rows: list[dict] = []
    try:
        for suite in SUITES:
            if suite in suites:
                rows += fns[suite]()
    finally:
        if "tmp" in cfg._cache:
            import shutil

            shutil.rmtree(cfg._cache.pop("tmp"), ignore_errors=True)
        cfg._cache.clear()
    return rows


def ratios(rows: list[dict], reference: str, suite: str = "splat") -> list[dict]:
    """Same-run ratios: for every (run, case, config without "round") of `suite`, the median over
    rounds of seconds(reference) / seconds(method) per method (> 1: the method is faster)."""
    groups: dict[tuple, dict[str, list[float]]] = {}
    for r in rows:
        if r.get("kind") != "speed" or r["suite"] != suite or r["seconds"] is None:
            continue
        cfg = {k: v for k, v in r["config"].items() if k != "round"}
        key = (r["run"], r["case"], json.dumps(cfg, sort_keys=True))
        groups.setdefault(key, {}).setdefault(r["method"], []).append(r["seconds"])
    out = []
    for (run_id, case, cfg), by in sorted(groups.items()):
        if reference not in by:
            continue
        ref = statistics.median(by[reference])
        for method, secs in sorted(by.items()):
            if method != reference:
                out.append(
                    {
                        "run": run_id,
                        "case": case,
                        "config": json.loads(cfg),
                        "method": method,
                        "reference": reference,
                        "ratio": ref / statistics.median(secs),
                    }
                )
    return out
