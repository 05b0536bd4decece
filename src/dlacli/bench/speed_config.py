"""The speed suites' settings and timers (`dla bench speed`, bench/speed.py): one SpeedConfig per
run, its smoke-test size, the one median-of-repeats timer every suite uses (also sent, as
source, to the fresh interpreter of each splat case), and the timer of one `dla` command in a
fresh interpreter (the startup and dream suites), and `run_isolated`, which runs a case in a fresh
interpreter, from this package or a baseline copy (the splat and render suites)."""

from __future__ import annotations

import inspect
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from dlacli.limits import DEFAULT_GAUSSIANS, FIT_STEPS, LIFT_STEPS

SUITES = ("startup", "splat", "body", "lift", "animate", "usd", "render", "view", "dream", "motion")
_N = DEFAULT_GAUSSIANS
SPLAT_CASES = ((2_048, 128), (20_000, 256), (20_000, 512), (65_536, 256), (65_536, 512), (_N, 256), (_N, 512))
DENSE_MAX_PAIRS = 2_048 * 128 * 128  # Gaussians x pixels up to which the dense path runs
USD_LIMBS = 16


@dataclass
class SpeedConfig:
    splat_cases: tuple[tuple[int, int], ...] = SPLAT_CASES
    splat_paths: tuple[str, ...] = ("numba", "torch", "dense")  # gsplat joins on CUDA
    repeats: int = 5
    torch_budget_s: float = 150.0  # a torch / dense case whose runs would take longer is skipped
    sh_degree: int = 0
    baseline: str | None = None  # another src folder holding a dlacli package, for splat and render ratios
    cold: bool = False  # splat: also time one first call with an empty numba cache (the JIT compile)
    rounds: int = 1
    gaussians: int = DEFAULT_GAUSSIANS  # body, animate, render
    frames: int = 30  # animate, render, usd
    res: int = 512  # lift subject, render size
    heatmap: str | None = None  # render: a folder for the compositing heat map of the frame it counts
    lift_steps: tuple[int, ...] = (0, LIFT_STEPS)
    seed: int = 1001  # the lift subject (a seed no test uses)
    startup_runs: int = 10
    usd_gaussians: int = DEFAULT_GAUSSIANS
    usd_schemas: tuple[str, ...] = ("points", "instancer")
    usd_tolerances_mm: tuple[float, ...] = (0.0, 1.0)
    dream_res: int = 512  # dream: the views' size
    dream_fit_steps: int = FIT_STEPS  # dream: the body fit's steps (dream's default)
    motion_clip: str = "walk"  # motion: the built-in motion the synthetic video shows
    motion_res: int = 320  # motion: the synthetic video's size
    motion_seconds: float = 10.0  # motion: its length (the clip forward and backward, at 30 fps)
    _cache: dict = field(default_factory=dict, repr=False)


def quick_config() -> SpeedConfig:
    """A smoke-test size of every suite (seconds on two cores)."""
    return SpeedConfig(
        splat_cases=((2_048, 64), (8_192, 128)),
        repeats=2,
        gaussians=8_192,
        frames=4,
        res=96,
        lift_steps=(0, 2),
        startup_runs=2,
        usd_gaussians=4_096,
        usd_tolerances_mm=(0.0,),
        dream_res=64,
        dream_fit_steps=3,
        motion_res=128,
        motion_seconds=0.5,
    )


def median_min(fn: Callable[[], object], repeats: int, sync: Callable[[], None] = lambda: None) -> tuple[float, float]:
    """(median, min) seconds of `repeats` calls after one warm-up call."""
    fn()
    sync()
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), min(times)


_PROBE = (
    "import sys\n"
    "from dlacli.cli.app import main\n"
    "try:\n"
    "    main(sys.argv[1:])\n"
    "except SystemExit:\n"
    "    pass\n"
    "print('torch-loaded=' + str('torch' in sys.modules), file=sys.stderr)\n"
)


def cli_seconds(argv: list[str]) -> tuple[float, bool]:
    """(wall seconds, whether torch got imported) of `dla *argv` in a fresh interpreter, as a user
    runs it (interpreter start, imports, the command, exit). Raises RuntimeError when it fails."""
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", _PROBE, *argv], capture_output=True, text=True, check=False)
    sec = time.perf_counter() - t0
    if "torch-loaded=" not in done.stderr or any(line.startswith("error:") for line in done.stderr.splitlines()):
        raise RuntimeError(f"dla {' '.join(argv[:2])} failed: {done.stderr.strip()[-300:]}")
    return sec, "torch-loaded=True" in done.stderr


def run_isolated(
    funcs: tuple[Callable, ...],
    args: list,
    pythonpath: str | None = None,
    numba_cache: str | None = None,
    sampled_rss: bool = False,
) -> dict:
    """Call funcs[-1](*args) in a fresh interpreter (the functions' source is sent with `python
    -c`, with median_min), importing dlacli from `pythonpath` first when given (a baseline copy of
    the package): -> the JSON dict it prints, or {"skipped": why} when it failed. `sampled_rss`:
    big blocks go to and from the OS at once (glibc's mmap threshold at 128 KiB), so that a
    sampled RSS follows them; slower, and only for a case that samples its peak memory."""
    src = "from __future__ import annotations\nimport statistics\nimport time\n\n" + "\n\n".join(
        inspect.getsource(f) for f in (median_min, *funcs)
    )
    src += f"\n\nimport json, sys\nprint(json.dumps({funcs[-1].__name__}(*json.loads(sys.argv[1]))))\n"
    env = dict(os.environ, OMP_WAIT_POLICY=os.environ.get("OMP_WAIT_POLICY", "PASSIVE"))
    if sampled_rss:
        env["MALLOC_MMAP_THRESHOLD_"] = str(128 * 1024)
    if numba_cache:
        env["NUMBA_CACHE_DIR"] = numba_cache
    if pythonpath:
        env["PYTHONPATH"] = os.pathsep.join(
            [pythonpath, *[p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]]
        )
    done = subprocess.run([sys.executable, "-c", src, json.dumps(args)], capture_output=True, text=True, env=env)
    if done.returncode != 0:
        return {"skipped": "failed: " + (done.stderr.strip().splitlines() or ["no output"])[-1][:200]}
    return json.loads(done.stdout.strip().splitlines()[-1])
