"""`dla bench`: accuracy, stability, Gaussian-budget and speed suites (tables on stdout; rows with --json / --jsonl)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional

import typer

from dlacli.bench.speed_config import SPLAT_CASES, SUITES, SpeedConfig, quick_config  # torch-free: the help quotes them
from dlacli.cli import options
from dlacli.limits import (
    BENCH_IMAGE_SIZE,
    BENCH_SEED,
    BUDGET_LADDER,
    DEFAULT_GAUSSIANS,
    FIT_STEPS,
    LIFT_STEPS,
    MAX_GAUSSIANS,
    MAX_IMAGE_SIZE,
    MAX_LIFT_RESOLUTION,
    MAX_LIFT_STEPS,
    MAX_LIST_CHARS,
    MAX_LIST_ITEMS,
    MAX_SEED,
    MIN_BENCH_IMAGE_SIZE,
    MIN_GAUSSIANS,
    MIN_IMAGE_SIZE,
)
from dlacli.stages.lift.methods import METHODS

bench_app = typer.Typer(
    help="Benchmarks: accuracy against cost, stability, the Gaussian budget and speed, on synthetic subjects.",
    no_args_is_help=True,
    context_settings={"help_option_names": ["-h", "--help"]},
)


_KNOWN = "; ".join(f"{m.name} ({m.about})" for m in METHODS.values())
_SPECS = (
    f"NAME[:KEY=VALUE,...] (dlacli.stages.lift.methods): {_KNOWN}; "
    f"e.g. unproject:steps={LIFT_STEPS},render_size=256 or learned:checkpoint=CKPT,steps=20"
)
_METHODS = f"unproject,unproject:steps={LIFT_STEPS}"  # --methods: mesh unprojection alone, and refined
_OLD_STEPS_HELP = (
    f"Refinement steps of the older spelling 'refine' (default {LIFT_STEPS}); write unproject:steps=N instead."
)
_SPEED, _QUICK = SpeedConfig(), quick_config()  # `dla bench speed`'s defaults, without and with --quick


def _size(default: int | None, help: str, flag: str = "--res") -> Any:
    """The image size of a benchmark's subjects (int, or Optional[int] with default None)."""
    return options.image_size(default, help, flag, minimum=MIN_BENCH_IMAGE_SIZE)


def _results(what: str) -> Any:
    """--jsonl FILE (Optional[Path]): where the rows are appended; `what` the help calls them."""
    help = f"Also append the {what} as dla.bench/1 JSON lines to this file (`dla bench report` reads it)."
    return options.side_output("--jsonl", help, (".jsonl",), "results file")


def _ints(text: str, name: str, hi: int) -> list[int]:
    from dlacli.errors import DlaInputError

    if len(text) > MAX_LIST_CHARS:
        raise DlaInputError(name, "is too long")
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise DlaInputError(name, f"expected comma-separated integers, got {text[:40]!r}") from None
    if not values:
        raise DlaInputError(name, "is empty")
    if len(values) > MAX_LIST_ITEMS or not all(0 <= v <= hi for v in values):
        raise DlaInputError(name, f"expected at most {MAX_LIST_ITEMS} integers in [0, {hi}]")
    return values


def _names(text: str, name: str, known) -> list[str]:
    from dlacli.errors import DlaInputError

    if len(text) > MAX_LIST_CHARS:
        raise DlaInputError(name, "is too long")
    values = [x.strip() for x in text.split(",") if x.strip()]
    if not values:
        raise DlaInputError(name, "is empty")
    unknown = [v for v in values if v not in known]
    if unknown:
        raise DlaInputError(name, f"unknown name {unknown[0]!r} (one of {', '.join(known)})")
    return list(dict.fromkeys(values))


def _cases(text: str) -> tuple[tuple[int, int], ...]:
    """ "N:RES,N:RES" -> ((N, RES), ...)."""
    from dlacli.errors import DlaInputError

    out = []
    for part in text[:MAX_LIST_CHARS].split(","):
        if not part.strip():
            continue
        try:
            n, res = (int(x) for x in part.split(":"))
        except ValueError:
            raise DlaInputError("--splat-cases", f"expected N:RES pairs, got {part.strip()[:40]!r}") from None
        if not (1 <= n <= MAX_GAUSSIANS and MIN_IMAGE_SIZE <= res <= MAX_IMAGE_SIZE):
            problem = f"N must be in [1, {MAX_GAUSSIANS}] and RES in [{MIN_IMAGE_SIZE}, {MAX_IMAGE_SIZE}]"
            raise DlaInputError("--splat-cases", f"{part.strip()}: {problem}")
        out.append((n, res))
    if not out or len(out) > MAX_LIST_ITEMS:
        raise DlaInputError("--splat-cases", f"expected 1 to {MAX_LIST_ITEMS} N:RES pairs")
    return tuple(out)


def _jsonl(path: Optional[Path]) -> Optional[Path]:
    """--jsonl (its suffix checked as it is parsed, `_results`): a file rows can be appended to,
    refused before the run when it is not (a folder, a link to one, a missing parent folder)."""
    from dlacli.io.atomic import check_outputs

    if path is not None:
        check_outputs(files=[path])
    return path


def _emit(rows: list[dict], jsonl: Optional[Path], as_json: bool, table) -> None:
    """Append the rows to --jsonl, then print them as JSON lines or as `table(rows)` (markdown)."""
    if jsonl is not None:
        from dlacli.bench.rows import append_rows

        append_rows(jsonl, rows)
    if as_json:
        for row in rows:
            typer.echo(json.dumps(row, sort_keys=True))
    else:
        typer.echo(table(rows))


def _stderr(line: str) -> None:
    import sys

    print(line, file=sys.stderr, flush=True)


@bench_app.command("pipeline")
def pipeline(
    seeds: str = typer.Option(
        f"{BENCH_SEED},{BENCH_SEED + 1}", "--seeds", help="Synthetic subjects (use seeds no test uses)."
    ),
    steps: str = typer.Option(f"0,{LIFT_STEPS},{3 * LIFT_STEPS}", "--steps", help="Refinement steps to compare."),
    res: int = _size(BENCH_IMAGE_SIZE, "Image size of the subjects."),
    as_json: bool = typer.Option(False, "--json", help="Print the full result as one JSON object."),
    jsonl: Optional[Path] = _results("runs"),
) -> None:
    """synth -> lift -> render: PSNR (whole image and inside the mask), SSIM and alpha IoU on 12
    novel views and 8 novel poses per subject, lift time per steps setting, animate time."""
    import sys

    from dlacli.bench.pipeline import markdown_table, result_rows, run

    jsonl = _jsonl(jsonl)
    result = run(
        _ints(seeds, "--seeds", MAX_SEED),
        _ints(steps, "--steps", MAX_LIFT_STEPS),
        res=res,
        log=lambda line: print(line, file=sys.stderr),
    )
    if jsonl is not None:
        from dlacli.bench.rows import append_rows

        append_rows(jsonl, result_rows(result))
    if as_json:
        typer.echo(json.dumps(result))
    else:
        typer.echo(markdown_table(result))
        typer.echo(f"animate {result['animate_frames']} frames (pose + USD): {result['animate_s_median']:.1f} s median")


@bench_app.command("accuracy")
def accuracy(
    seeds: str = typer.Option(
        "9001,9002",
        "--seeds",
        help="Synthetic subjects reserved for benchmarking (no test or training uses 9000-9999).",
    ),
    methods: str = typer.Option(_METHODS, "--methods", help="Methods to compare, comma-separated: " + _SPECS + "."),
    res: int = _size(BENCH_IMAGE_SIZE, f"Image size (the paper's protocol: {BENCH_IMAGE_SIZE}, black background)."),
    appearance: str = typer.Option(
        "lit", "--appearance", help="Subjects' appearance: lit (pose- and view-dependent shading) or albedo."
    ),
    wardrobe: str = typer.Option(
        "heldout", "--wardrobe", help="Subjects' garments: heldout (none a training subject wore), full, default."
    ),
    input: str = typer.Option(
        "views",
        "--input",
        help="What is lifted: views (the subject's 4 true views) or photo (its front view alone, through dla dream).",
    ),
    backend: str = typer.Option(
        "body", "--backend", help="With --input photo: dream backends to compare, comma-separated (e.g. shell,body)."
    ),
    fit_steps: int = typer.Option(
        FIT_STEPS, "--fit-steps", min=3, max=100_000, help="With --input photo: dream's body-fit steps (as dla dream)."
    ),
    keep: Optional[Path] = typer.Option(
        None,
        "--subjects",
        help="Keep the synthetic subjects in this folder and reuse those already there (same seed and settings).",
    ),
    prior: str = typer.Option(
        "none",
        "--prior",
        help="With --input photo: the body backend's completion priors to compare, comma-separated (none, shipped, "
        "checkpoint folders; as dla dream --prior).",
    ),
    oracles: bool = typer.Option(
        False,
        "--oracles",
        help="With --input photo: the error budget's rows too: the dream on the true body, the fitted body with the "
        "true colours, and the four true views (config oracle=true_body|true_colours|four_views).",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the rows as JSON lines instead of a table."),
    jsonl: Optional[Path] = _results("rows"),
) -> None:
    """Accuracy against cost of every method: lift in a fresh process (wall time, peak memory),
    then PSNR (whole image and inside the mask), SSIM and alpha IoU on novel views, novel poses
    and novel view & pose. LPIPS is absent: it needs AlexNet weights dla does not ship. With
    --input photo the subject's front view is the photo: dream -> lift, scored after aligning the
    dream's world to the subject's through the bodies, plus the dreamed views (docs/dream.md)."""
    from dlacli.bench.accuracy import run
    from dlacli.bench.report import report_markdown
    from dlacli.data.appearance import APPEARANCES
    from dlacli.data.subject import WARDROBES
    from dlacli.stages.lift.methods import parse_methods

    specs = parse_methods(methods)
    _names(appearance, "--appearance", APPEARANCES)
    _names(wardrobe, "--wardrobe", WARDROBES)
    for spec in specs:
        if "checkpoint" in spec.options() and not Path(spec.options()["checkpoint"]).exists():
            from dlacli.errors import DlaInputError

            raise DlaInputError("--methods", f"{spec.label}: no such checkpoint folder")
    jsonl = _jsonl(jsonl)
    from dlacli.bench.single_photo import INPUTS, check_backends, run_photo

    _names(input, "--input", INPUTS)
    seed_list = _ints(seeds, "--seeds", MAX_SEED)
    if keep is not None and keep.exists() and not keep.is_dir():
        from dlacli.errors import DlaInputError

        raise DlaInputError("--subjects", f"{keep} is not a folder")
    common = dict(res=res, appearance=appearance, wardrobe=wardrobe, log=_stderr, keep=keep)
    if oracles and input != "photo":
        from dlacli.errors import DlaInputError

        raise DlaInputError("--oracles", "applies to --input photo only")
    if input == "photo":
        backends = check_backends(backend.split(","))
        priors = [p.strip() for p in prior.split(",") if p.strip()]
        rows = run_photo(seed_list, specs, backends, fit_steps=fit_steps, oracles=oracles, priors=priors, **common)
    else:
        rows = run(seed_list, specs, **common)
    _emit(rows, jsonl, as_json, lambda r: report_markdown(r, None))


@bench_app.command("regions")
def regions(
    seed: int = options.seed("Synthetic subject (use a seed no test uses).", default=BENCH_SEED),
    steps: int = typer.Option(LIFT_STEPS, "--steps", min=0, max=MAX_LIFT_STEPS, help="Lift refinement steps."),
    res: int = _size(BENCH_IMAGE_SIZE, "Image size of the subject."),
    output: Optional[Path] = options.output(
        "Error picture (.png): ground truth | render | error x4 | regions, an input view above a novel view.",
        (".png",),
        "image",
        required=False,
    ),
) -> None:
    """Where the error lives: synth -> lift, then masked PSNR per body region (face, hair, hands,
    arms, torso, legs, feet, off body, silhouette band) on the input views and the novel views."""
    import tempfile

    import numpy as np
    from PIL import Image

    from dlacli.bench.regions import REGIONS, error_picture, pixel_regions, region_psnr
    from dlacli.bench.score import render_split
    from dlacli.body.model import get_body_model
    from dlacli.data.synth import synth
    from dlacli.io.atomic import atomic_path, check_outputs
    from dlacli.io.views import read_views
    from dlacli.stages.lift.methods import make_spec

    check_outputs(files=[output])
    rows, pictures = [], []
    with tempfile.TemporaryDirectory() as tmp:
        folder = synth(seed, Path(tmp) / "subject", res=res, novel_views=4, novel_poses=0)
        views = read_views(folder)
        avatar = make_spec("unproject", steps=steps).lift(views).avatar
        verts = get_body_model().forward_body(views.body).vertices[0].numpy()
        for split, vs in (
            ("input views", views),
            ("novel views", read_views(folder / "novel_views", require_body=False)),
        ):
            rgba, gt = render_split(avatar, vs)
            pred = rgba[..., :3]
            labels = pixel_regions(verts, vs.cameras, vs.masks)
            rows.append((split, region_psnr(pred, gt, labels)))
            pictures.append(error_picture(gt[0], pred[0], labels[0]))
    typer.echo("| region | " + " | ".join(f"{split}: masked PSNR / pixels / error share" for split, _ in rows) + " |")
    typer.echo("|---|" + "---|" * len(rows))
    for name in REGIONS:
        cells = [
            f"{r[name]['psnr']:.2f} / {r[name]['pixels']:.0%} / {r[name]['error']:.0%}" if name in r else "-"
            for _, r in rows
        ]
        typer.echo(f"| {name} | " + " | ".join(cells) + " |")
    if output is not None:
        with atomic_path(output) as tmp:
            Image.fromarray(np.concatenate(pictures, axis=0)).save(tmp)


@bench_app.command("speed")
def speed(
    suite: str = typer.Option(
        ",".join(SUITES), "--suite", help=f"Suites to run, comma-separated: {', '.join(SUITES)}."
    ),
    quick: bool = typer.Option(False, "--quick", help="Tiny sizes of every suite (a smoke run, seconds)."),
    repeats: Optional[int] = typer.Option(
        None,
        "--repeats",
        min=1,
        max=1000,
        help=f"Timed calls per case (default {_SPEED.repeats}; --quick {_QUICK.repeats}).",
    ),
    gaussians: Optional[str] = options.gaussians(
        help=f"Gaussians of the body, animate and render suites (default {_SPEED.gaussians:,})."
    ),
    res: Optional[int] = _size(None, f"Image size of the lift subject and the render suite (default {_SPEED.res})."),
    frames: Optional[int] = typer.Option(
        None,
        "--frames",
        min=1,
        max=10_000,
        help=f"Frames of the animate, usd and render suites (default {_SPEED.frames}).",
    ),
    lift_steps: Optional[str] = typer.Option(
        None,
        "--lift-steps",
        help=f"lift: refinement steps to time, comma-separated (default {','.join(map(str, _SPEED.lift_steps))}).",
    ),
    splat_cases: Optional[str] = typer.Option(
        None,
        "--splat-cases",
        metavar="N:RES,...",
        help=(
            f"splat: Gaussian counts and image sizes, e.g. 20000:256,{DEFAULT_GAUSSIANS}:512 "
            f"(default {','.join(f'{n}:{r}' for n, r in SPLAT_CASES)})."
        ),
    ),
    no_torch: bool = typer.Option(False, "--no-torch", help="splat: skip the slow pure-torch and dense paths."),
    baseline: Optional[Path] = typer.Option(
        None,
        "--baseline",
        help=(
            "splat and render: also time another copy of the package (a src folder holding dlacli), alternated "
            "with this one; the report shows baseline / current."
        ),
    ),
    cold: bool = typer.Option(
        False, "--cold", help="splat: also time a first call with an empty numba cache (the JIT compile)."
    ),
    rounds: int = typer.Option(
        1, "--rounds", min=1, max=100, help="With --baseline: alternate the two versions this many times per case."
    ),
    heatmap: Optional[Path] = typer.Option(
        None,
        "--heatmap",
        help=(
            "render: write the compositing heat map of one walk frame (Gaussians per tile, kernel evaluations, "
            "Gaussians covering and composited per pixel) as a PNG in this folder."
        ),
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the rows as JSON lines instead of tables."),
    jsonl: Optional[Path] = _results("rows"),
) -> None:
    """Speed: splatting forward and forward+backward per Gaussian count and image size (numba vs
    the pure-torch renderer; gsplat on CUDA), pose + skin per frame, lift and animate stage times,
    USD write throughput, animation frames per second, CLI start-up. Medians; never a test."""
    from dataclasses import replace

    from dlacli.bench.report import speed_markdown
    from dlacli.bench.speed import run
    from dlacli.errors import DlaInputError

    suites = _names(suite, "--suite", SUITES)
    jsonl = _jsonl(jsonl)
    if baseline is not None and not (baseline / "dlacli" / "__init__.py").is_file():
        raise DlaInputError(baseline, "is not a src folder holding a dlacli package (no dlacli/__init__.py)")
    cfg = quick_config() if quick else SpeedConfig()
    changes = {
        k: v
        for k, v in (("repeats", repeats), ("gaussians", gaussians), ("res", res), ("frames", frames))
        if v is not None
    }
    if lift_steps is not None:
        changes["lift_steps"] = tuple(_ints(lift_steps, "--lift-steps", MAX_LIFT_STEPS))
    if splat_cases is not None:
        changes["splat_cases"] = _cases(splat_cases)
    if no_torch:
        changes["splat_paths"] = ("numba",)
    if cold:
        changes["cold"] = True
    if baseline is not None:
        changes.update(baseline=str(baseline.resolve()), rounds=rounds)
    if heatmap is not None:
        if heatmap.exists() and not heatmap.is_dir():
            raise DlaInputError(heatmap, "is not a folder")
        changes["heatmap"] = str(heatmap)
    rows = run(suites, replace(cfg, **changes), log=_stderr)
    _emit(rows, jsonl, as_json, lambda r: "\n".join(speed_markdown(r, intro=False)).rstrip())


@bench_app.command("stability")
def stability(
    seeds: str = typer.Option(str(BENCH_SEED), "--seeds", help="Synthetic subjects (use seeds no test uses)."),
    methods: str = typer.Option(_METHODS, "--methods", help="Methods to compare, comma-separated: " + _SPECS + "."),
    steps: Optional[int] = typer.Option(None, "--steps", min=1, max=MAX_LIFT_STEPS, help=_OLD_STEPS_HELP),
    checkpoint: Optional[Path] = options.checkpoint(
        "A dla train checkpoint for the methods named 'learned' without checkpoint=."
    ),
    perturbations: Optional[str] = typer.Option(
        None,
        "--perturbations",
        help=(
            "Comma-separated subset (default all): pose_noise, shape_noise, colour_shift, misregister_px, "
            "misregister_deg, fewer_views, extreme_pose, self_contact, small_in_frame, large_in_frame."
        ),
    ),
    levels: Optional[int] = typer.Option(
        None,
        "--levels",
        min=2,
        max=100,
        help="At most this many levels per perturbation, the clean one and the worst included (default all).",
    ),
    res: int = _size(256, "Image size of the subjects."),
    as_json: bool = typer.Option(False, "--json", help="Print the rows as JSON lines instead of tables."),
    jsonl: Optional[Path] = _results("runs"),
) -> None:
    """Degradation curves: each method lifts perturbed inputs (noisy body pose and shape,
    colour-shifted and misregistered views, fewer views, extreme poses and self-contact, the
    person small or large in frame); masked PSNR on novel views and poses per level, the level
    where it has dropped 2 dB, and every NaN, exception or empty avatar."""
    from dlacli.bench.report import stability_markdown
    from dlacli.bench.stability import PERTURBATIONS, run
    from dlacli.stages.lift.methods import parse_methods

    fill = {"checkpoint": str(checkpoint)} if checkpoint is not None else None
    specs = parse_methods(methods, refine_steps=steps or LIFT_STEPS, fill=fill, flags={"checkpoint": "--checkpoint"})
    specs = list({(s.name, json.dumps(s.options(), sort_keys=True)): s for s in specs}.values())  # each once
    perts = _names(perturbations, "--perturbations", list(PERTURBATIONS)) if perturbations else None
    jsonl = _jsonl(jsonl)
    rows = run(_ints(seeds, "--seeds", MAX_SEED), specs, perts, res=res, levels=levels, log=_stderr)
    _emit(rows, jsonl, as_json, lambda r: "\n".join(stability_markdown(r, intro=False)).rstrip())


@bench_app.command("budget")
def budget(
    seeds: str = typer.Option(str(BENCH_SEED), "--seeds", help="Synthetic subjects (use seeds no test uses)."),
    counts: str = typer.Option(",".join(map(str, BUDGET_LADDER)), "--counts", help="Gaussian counts to compare."),
    uv: str = typer.Option(
        "128,256,512", "--uv", help="UV resolutions of the Gaussian map (lift --resolution) to compare."
    ),
    size: int = _size(
        BENCH_IMAGE_SIZE, "The target render size: the subjects' views are rendered and scored at it.", "--size"
    ),
    method: str = typer.Option(
        "unproject", "--method", help="The method making the avatars (one that takes resolution=): " + _SPECS + "."
    ),
    steps: Optional[int] = typer.Option(None, "--steps", min=1, max=MAX_LIFT_STEPS, help=_OLD_STEPS_HELP),
    usd_frames: int = typer.Option(
        8, "--usd-frames", min=0, max=1000, help="Frames of the walk written as USD per count (0: no USD sizes)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the rows as JSON lines instead of tables."),
    jsonl: Optional[Path] = _results("runs"),
) -> None:
    """The Gaussian budget: masked PSNR against the number of Gaussians and the UV resolution at a
    render size, with render time and USD size per count, and what `--gaussians auto` picks."""
    from dlacli.bench.budget import run
    from dlacli.bench.report import budget_markdown
    from dlacli.stages.lift.methods import parse_method

    spec = parse_method(method, refine_steps=steps or LIFT_STEPS)
    uvs = _ints(uv, "--uv", MAX_LIFT_RESOLUTION)
    spec.with_options("--method", resolution=uvs[0])  # one that takes the UV resolution
    ns = _ints(counts, "--counts", MAX_GAUSSIANS)
    if min(ns) < MIN_GAUSSIANS:
        from dlacli.errors import DlaInputError

        raise DlaInputError("--counts", f"every count must be at least {MIN_GAUSSIANS}")
    jsonl = _jsonl(jsonl)
    rows = run(
        _ints(seeds, "--seeds", MAX_SEED), ns, uvs, render_size=size, method=spec, usd_frames=usd_frames, log=_stderr
    )
    _emit(rows, jsonl, as_json, lambda r: "\n".join(budget_markdown(r, intro=False)).rstrip())


@bench_app.command("report")
def report(
    results: Path = typer.Argument(
        ...,
        metavar="RESULTS",
        help="dla.bench/1 JSON lines (`dla bench pipeline / stability / budget / speed --jsonl`).",
    ),
    output: Path = options.output(
        "The markdown page; its charts are written beside it: <name>.png (time against accuracy), "
        "<name>_stability.png, <name>_budget.png.",
        (".md",),
        "Markdown page",
        default=Path("docs/benchmarks.md"),
    ),
) -> None:
    """Regenerate the benchmark page (tables per split, the Pareto frontier, the time-vs-accuracy
    chart; the stability curves, the Gaussian budget and the speed tables when the rows hold
    them) from result rows, so the page never drifts from the numbers."""
    from dlacli.bench.charts import draw_budget_chart, draw_chart, draw_stability_chart
    from dlacli.bench.report import report_markdown
    from dlacli.bench.rows import kind, read_rows
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import atomic_path, check_outputs, output_group

    chart = output.with_suffix(".png")
    stab_chart = output.with_name(output.stem + "_stability.png")
    budget_chart = output.with_name(output.stem + "_budget.png")
    check_outputs(files=[output, chart, stab_chart, budget_chart], inputs=[results])
    rows = read_rows(results)
    if not rows:
        raise DlaInputError(results, "holds no result rows")
    kinds = {kind(r) for r in rows}
    with output_group():
        if "accuracy" in kinds:
            draw_chart(rows, chart)
        if "stability" in kinds:
            draw_stability_chart(rows, stab_chart)
        if "budget" in kinds:
            draw_budget_chart(rows, budget_chart)
        page = report_markdown(
            rows,
            chart.name if "accuracy" in kinds else None,
            stability_chart=stab_chart.name if "stability" in kinds else None,
            budget_chart=budget_chart.name if "budget" in kinds else None,
        )
        with atomic_path(output) as tmp:
            tmp.write_text(page + "\n", encoding="utf-8")
    typer.echo(str(output))


def register(app: typer.Typer) -> None:
    app.add_typer(bench_app, name="bench")
