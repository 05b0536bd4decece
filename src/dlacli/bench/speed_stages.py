"""Speed suites of whole stages (`dla bench speed`, bench/speed.py): lift, animate, the USD
writer and the animation renderer, on one synthetic subject made once per run, and dream on the
bundled sample photo."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from dlacli.bench.speed_config import USD_LIMBS, SpeedConfig, cli_seconds, median_min, run_isolated


def _subject_and_avatar(cfg: SpeedConfig, log):
    """(view folder, its ViewSet, an unprojected avatar at cfg.gaussians), made once per run."""
    if "avatar" not in cfg._cache:
        from dlacli.data.synth import synth
        from dlacli.io.views import read_views
        from dlacli.stages.lift.methods import make_spec

        tmp = tempfile.mkdtemp(prefix="dla-speed-")
        cfg._cache["tmp"] = tmp
        t0 = time.perf_counter()
        folder = synth(cfg.seed, Path(tmp) / "subject", res=cfg.res, novel_views=0, novel_poses=0)
        cfg._cache["synth_s"] = time.perf_counter() - t0
        views = read_views(folder)
        cfg._cache["views"] = views
        cfg._cache["avatar"] = make_spec("unproject", steps=0, gaussians=cfg.gaussians).lift(views).avatar
    return cfg._cache["views"], cfg._cache["avatar"]


def _walk(frames: int):
    import numpy as np

    from dlacli.body.builtin_motions import builtin_motion
    from dlacli.types import Motion

    walk = builtin_motion("walk")
    idx = np.arange(frames) % walk.num_frames
    return Motion(walk.bone_labels, walk.rotations[idx], walk.root_rotation[idx], walk.root_translation[idx], walk.fps)


def lift_suite(cfg: SpeedConfig, row, log) -> list[dict]:
    from dlacli.stages.lift.methods import make_spec

    views, _ = _subject_and_avatar(cfg, log)
    out = [row("lift", "synth", "cpu", {"res": cfg.res, "seed": cfg.seed}, cfg._cache["synth_s"], 1)]
    for steps in cfg.lift_steps:
        t0 = time.perf_counter()
        make_spec("unproject", steps=steps, gaussians=cfg.gaussians).lift(views)
        sec = time.perf_counter() - t0
        out.append(row("lift", "lift", "cpu", {"res": cfg.res, "steps": steps, "gaussians": cfg.gaussians}, sec, 1))
        log(f"lift {steps} steps at {cfg.res} px: {sec:.1f} s")
    return out


def animate_suite(cfg: SpeedConfig, row, log) -> list[dict]:
    from dlacli.stages.animate import pose_avatar, write_animation

    _, avatar = _subject_and_avatar(cfg, log)
    clip = _walk(cfg.frames)
    c = {"gaussians": cfg.gaussians, "frames": cfg.frames}
    t0 = time.perf_counter()
    anim = pose_avatar(avatar, clip, cfg.gaussians)
    pose_s = time.perf_counter() - t0
    path = Path(cfg._cache["tmp"]) / "anim.usdc"
    t0 = time.perf_counter()
    write_animation(anim, path, "points", 0.001)
    usd_s = time.perf_counter() - t0
    log(
        f"animate {cfg.frames} frames x {cfg.gaussians} Gaussians: pose {pose_s / cfg.frames * 1e3:.1f} ms/frame, "
        f"USD {usd_s:.2f} s"
    )
    return [
        row("animate", "pose", "cpu", c, pose_s / cfg.frames, 1, items=cfg.frames),
        row(
            "animate",
            "usd_write",
            "cpu",
            {**c, "schema": "points", "tolerance_mm": 1.0},
            usd_s,
            1,
            size_mib=path.stat().st_size / 2**20,
            items=cfg.frames,
        ),
    ]


def walk_like(t: int, n: int, fps: float = 30.0, seed: int = 0):
    """A synthetic walk-like motion of n Gaussians over t frames: 16 "limbs" swing +-30 degrees at
    1 Hz about their own pivots while the body moves forward at 1.3 m/s and bobs 2 cm at 2 Hz (random
    per-frame positions would be a worst case no compaction helps) -> positions [T, N, 3], quats
    [T, N, 4] (w, x, y, z), scales [N, 3], rgb [N, 3], opacities [N], float32."""
    import numpy as np

    rng = np.random.default_rng(seed)
    limb = rng.integers(0, USD_LIMBS, n)
    pivot = rng.uniform([-0.3, -0.1, -0.9], [0.3, 0.1, 0.6], (USD_LIMBS, 3))
    base = pivot[limb] + rng.normal(0, 0.08, (n, 3))
    phase = rng.uniform(0, 2 * np.pi, USD_LIMBS)
    secs = np.arange(t) / fps
    angle = np.radians(30) * np.sin(2 * np.pi * secs[:, None] + phase)  # [T, LIMBS] about +X
    c, s = np.cos(angle)[:, limb], np.sin(angle)[:, limb]
    rel = base - pivot[limb]
    positions = np.stack(
        [np.broadcast_to(rel[:, 0], c.shape), c * rel[:, 1] - s * rel[:, 2], s * rel[:, 1] + c * rel[:, 2]], -1
    )
    positions += pivot[limb]
    positions[..., 1] -= 1.3 * secs[:, None]
    positions[..., 2] += 0.02 * np.sin(4 * np.pi * secs)[:, None]
    quats = np.stack([np.cos(angle / 2)[:, limb], np.sin(angle / 2)[:, limb], np.zeros_like(c), np.zeros_like(c)], -1)
    scales = rng.uniform(0.001, 0.005, size=(n, 3))
    rgb, opacities = rng.uniform(size=(n, 3)), rng.uniform(0.5, 1, size=n)
    return [a.astype(np.float32) for a in (positions, quats, scales, rgb, opacities)]


def usd_suite(cfg: SpeedConfig, row, log) -> list[dict]:
    from dlacli.io.usd import write_usd

    n, t = cfg.usd_gaussians, cfg.frames
    positions, quats, scales, rgb, opacities = walk_like(t, n)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "anim.usdc"
        write_usd(path, positions[:1, :8], quats[:1, :8], scales[:8], rgb[:8], opacities[:8], 30.0)  # import pxr first
        for schema in cfg.usd_schemas:
            for tol in cfg.usd_tolerances_mm:

                def write(schema=schema, tol=tol):
                    write_usd(path, positions, quats, scales, rgb, opacities, 30.0, schema=schema, tolerance=tol / 1000)

                repeats = max(1, min(cfg.repeats, 3))
                med, lo = median_min(write, repeats)
                size = path.stat().st_size / 2**20
                out.append(
                    row(
                        "usd",
                        "write",
                        "cpu",
                        {"gaussians": n, "frames": t, "schema": schema, "tolerance_mm": tol},
                        med,
                        repeats,
                        min_seconds=lo,
                        size_mib=size,
                        items=n * t,
                    )
                )
                log(
                    f"usd {schema} tolerance {tol} mm: {med:.2f} s, {size:.1f} MiB ({n * t / med / 1e6:.1f} M "
                    "Gaussian-frames/s)"
                )
    return out


def _playback_case(avatar_path: str, gaussians: int, frames: int, res: int, repeats: int) -> dict:
    """Per frame: posing the built-in walk (`pose_avatar`) and splatting it from the following
    camera (`animation_preview_frames`), (median, min) seconds over `repeats` passes each. Sent as
    source to a fresh interpreter with `_walk` (`run_isolated`): it imports only APIs a baseline
    shares."""
    from dlacli.io.avatar import read_avatar
    from dlacli.stages.animate import animation_preview_frames, pose_avatar

    avatar = read_avatar(avatar_path)
    clip = _walk(frames)
    pose = median_min(lambda: pose_avatar(avatar, clip, gaussians), repeats)
    anim = pose_avatar(avatar, clip, gaussians)
    splat = median_min(lambda: sum(1 for _ in animation_preview_frames(anim, res)), repeats)
    return {"pose": [t / frames for t in pose], "splat": [t / frames for t in splat]}


def render_suite(cfg: SpeedConfig, row, log) -> list[dict]:
    """Playback on the CPU: posing the walk (body, tangent frames, skinning, the decoder's
    per-frame colour) and splatting its frames from the following camera, each a median over
    cfg.repeats passes, and their sum per frame (what a player that poses and draws each frame
    spends); with cfg.baseline, this package and the baseline copy alternate for cfg.rounds rounds,
    each in a fresh interpreter (methods "cpu" and "cpu_baseline"); then a turntable of the
    resting avatar."""
    from dlacli.io.avatar import write_avatar
    from dlacli.stages.render import render_avatar, turntable_cameras

    _, avatar = _subject_and_avatar(cfg, log)
    k = cfg.frames
    f = {"gaussians": cfg.gaussians, "size": cfg.res, "frames": k}
    path = Path(cfg._cache["tmp"]) / "playback.npz"
    write_avatar(avatar, path)
    todo = [("cpu", None, 0)]
    if cfg.baseline:
        pairs = [(("cpu", None), ("cpu_baseline", cfg.baseline))] * max(1, cfg.rounds)
        todo = [(m, src, r) for r, pair in enumerate(pairs) for m, src in (pair if r % 2 == 0 else pair[::-1])]
    out = []
    for method, src, rnd in todo:
        rec = run_isolated((_walk, _playback_case), [str(path), cfg.gaussians, k, cfg.res, cfg.repeats], src)
        c = {**f, **({"round": rnd} if cfg.baseline else {})}
        if "skipped" in rec:
            log(f"render {method}: skipped ({rec['skipped']})")
            out.append(row("render", "playback_frame", method, c, None, 0, skipped=rec["skipped"]))
            continue
        (pose, pose_lo), (splat, splat_lo) = rec["pose"], rec["splat"]
        log(
            f"render {method} {cfg.gaussians} Gaussians at {cfg.res} px: pose {pose * 1e3:.1f} ms + splat "
            f"{splat * 1e3:.1f} ms per frame = playback {1 / (pose + splat):.1f} fps (splat alone {1 / splat:.1f} fps)"
        )
        out += [
            row("render", "pose_frame", method, c, pose, cfg.repeats, min_seconds=pose_lo, items=1),
            row("render", "animation_frame", method, c, splat, cfg.repeats, min_seconds=splat_lo, items=1),
            row("render", "playback_frame", method, c, pose + splat, cfg.repeats, items=1),
        ]
    cams = turntable_cameras(avatar, 8, cfg.res)
    t0 = time.perf_counter()
    list(render_avatar(avatar, cams, [None] * 8, n_gaussians=cfg.gaussians))
    per_image = (time.perf_counter() - t0) / 8
    log(f"render {cfg.gaussians} Gaussians at {cfg.res} px: turntable {per_image * 1e3:.0f} ms/image")
    turntable = {"gaussians": cfg.gaussians, "size": cfg.res, "cameras": 8}
    out.append(row("render", "turntable_image", "cpu", turntable, per_image, 8, items=1))
    return out + [_composite_counts(cfg, avatar, row, log)]


def _composite_counts(cfg: SpeedConfig, avatar, row, log) -> dict:
    """Where a playback frame's compositing time goes: the walk's first frame from the following
    camera, rendered by the exact kernel (median ms) with its counts per pixel
    (dlacli.render.splat_stats); with cfg.heatmap, their heat map as a PNG there."""
    import torch

    from dlacli.avatar.posed import render_set
    from dlacli.render.splat_stats import composite_stats
    from dlacli.stages.animate import follow_cameras, pose_avatar

    anim = pose_avatar(avatar, _walk(1), cfg.gaussians)
    g, cam = anim.frame(0), follow_cameras(anim.pelvis, anim.fps, cfg.res).select(0)

    def render():
        with torch.no_grad():
            render_set(g, cam)

    med, lo = median_min(render, cfg.repeats)
    stats = composite_stats(g, cam)
    counts = {k: round(v, 3) for k, v in stats.summary().items()}
    if counts["covered_share"]:
        log(
            f"render {cfg.gaussians} Gaussians at {cfg.res} px, one walk frame: {counts['covered_share']:.0%} of "
            f"pixels covered; a listed tile: {counts['listed_per_tile']:.0f} Gaussians, "
            f"{counts['evaluations_per_pixel']:.1f} evaluations per pixel; a covered pixel: "
            f"{counts['covering_per_pixel']:.1f} covering, {counts['contributing_per_pixel']:.1f} composited"
        )
    if cfg.heatmap:
        from dlacli.bench.charts import composite_heatmap

        path = Path(cfg.heatmap) / f"composite_{cfg.gaussians}_{cfg.res}px.png"
        composite_heatmap(stats, path, f"{cfg.gaussians:,} Gaussians, {cfg.res} x {cfg.res}, one walk frame")
        log(f"render: heat map {path}")
    c = {"gaussians": cfg.gaussians, "size": cfg.res}
    return row("render", "composite_frame", "cpu", c, med, cfg.repeats, min_seconds=lo, items=1, counts=counts)


def view_suite(cfg: SpeedConfig, row, log) -> list[dict]:
    """The `dla view` page of the walk in headless Chromium (software WebGL2): its own timing of
    cfg.frames successive frames at cfg.res x cfg.res (bench/browser.py `time_page`)."""
    from dlacli.bench.browser import chromium, time_page
    from dlacli.stages.view import view_page, write_page

    c = {"gaussians": cfg.gaussians, "size": cfg.res, "frames": cfg.frames, "browser": "chromium-swiftshader"}
    if chromium() is None:
        log("view: skipped (headless Chromium not installed)")
        return [row("view", "page_frame", "cpu", c, None, 0, skipped="headless Chromium not installed")]
    _, avatar = _subject_and_avatar(cfg, log)
    tmp = Path(cfg._cache["tmp"])
    page = tmp / "walk.html"
    write_page(view_page(avatar, _walk(cfg.frames), cfg.gaussians), page)
    t = time_page(page, cfg.res, cfg.res, cfg.frames, tmp / "chromium-profile")
    log(
        f"view page {cfg.gaussians} Gaussians at {cfg.res} px: {t['fps']:.1f} fps "
        f"(JS {t['js_ms']:.0f} ms, GL {t['gl_ms']:.0f} ms per frame)"
    )
    return [
        row("view", "page_frame", "cpu", c, 1.0 / t["fps"], cfg.frames, items=1),
        row("view", "page_js", "cpu", c, t["js_ms"] / 1e3, cfg.frames, items=1),
        row("view", "page_gl", "cpu", c, t["gl_ms"] / 1e3, cfg.frames, items=1),
    ]


def dream_suite(cfg: SpeedConfig, row, log) -> list[dict]:
    """`dla dream` on the sample photo: the whole command (fresh interpreters; one warm-up run
    fills the on-disk caches) and its stages in this process (see bench/speed.py)."""
    import statistics

    import numpy as np

    from dlacli.io.detect import detect_person
    from dlacli.io.photo import read_photo
    from dlacli.paths import sample_keypoints, sample_photo
    from dlacli.stages.dream import views as D
    from dlacli.stages.dream.completion import SHIPPED as SHIPPED_PRIOR
    from dlacli.stages.dream.completion import load_prior
    from dlacli.stages.dream.plausibility import plausibility
    from dlacli.stages.dream.shell import template_views
    from dlacli.stages.dream.texture import body_views
    from dlacli.stages.fit.photo import fit_body
    from dlacli.stages.fit.report import overlay_png

    photo, res, steps = sample_photo(), cfg.dream_res, cfg.dream_fit_steps
    c = {"res": res, "fit_steps": steps}  # the command rows
    out = []
    with tempfile.TemporaryDirectory(prefix="dla-speed-dream-") as tmp:
        argv = ["dream", str(photo), "-o", str(Path(tmp) / "cli"), "--res", str(res), "--fit-steps", str(steps)]
        cli_seconds(argv)  # warm-up: caches on disk, .pyc files, the file-system cache
        for case, extra in (("command", []), ("command_keypoints", ["--keypoints", str(sample_keypoints())])):
            times = [cli_seconds(argv + extra)[0] for _ in range(max(1, cfg.repeats))]
            med = statistics.median(times)
            out.append(row("dream", case, "cli", c, med, len(times), min_seconds=min(times)))
            log(f"dream {case} at {res} px: {med:.1f} s (min {min(times):.1f} s)")

        image, mask, _ = read_photo(photo, notes=[])  # the sample's alpha is the person mask
        mask = np.asarray(mask, np.float32)
        timed = {}

        def stage(case, fn, config):
            t0 = time.perf_counter()
            timed[case] = fn()
            first = time.perf_counter() - t0
            med, lo = median_min(fn, cfg.repeats)
            out.append(row("dream", case, "cpu", config, med, cfg.repeats, min_seconds=lo, first_seconds=first))
            log(f"dream {case}: {med * 1e3:.0f} ms (first call {first * 1e3:.0f} ms)")

        stage("detect", lambda: detect_person(image, alpha=mask), {})
        det = timed["detect"]
        kps = np.asarray(det.keypoints, np.float32)
        stage("fit", lambda: fit_body(image, mask, kps, steps=steps, landmarks_3d=det.world), {"fit_steps": steps})
        fit = timed["fit"]

        def framed_views(make):
            rgb, alpha, cam = D.frame_crop(image, mask, fit.camera, res)
            return make(rgb, alpha, cam, fit.vertices)

        stage("views_body", lambda: framed_views(body_views), {"res": res})
        if SHIPPED_PRIOR.is_dir():  # the completion prior on top (dla dream --prior shipped)
            net = load_prior("shipped")
            prior_views = lambda *a: body_views(*a, prior=net)  # noqa: E731
            stage("views_body_prior", lambda: framed_views(prior_views), {"res": res, "prior": "shipped"})
        stage("views_shell", lambda: framed_views(template_views), {"res": res})
        images, masks, cams, _ = timed["views_body"]
        stage("plausibility", lambda: plausibility(images, masks, cams, fit.vertices), {"res": res})
        folder = D.build_views(image, mask, fit, res=res)

        def write():
            return D.write_dream_folder(folder, overlay_png(image * mask[..., None], fit), Path(tmp) / "stage")

        stage("write", write, {"res": res})
    return out


def _motion_clip(name: str):
    """A built-in motion (`dla motion` names it), at 30 fps."""
    from dlacli.stages.motion.source import load_motion

    return load_motion(name, fps=30.0)


def _installed_landmarks() -> list[str]:
    """The default landmark model, then the others that are installed (io.detect.landmark_model)."""
    from dlacli.errors import DlaInputError
    from dlacli.io.detect import landmark_model
    from dlacli.limits import DEFAULT_LANDMARKS, LANDMARKS

    out = [DEFAULT_LANDMARKS]
    for name in LANDMARKS:
        if name == DEFAULT_LANDMARKS:
            continue
        try:
            landmark_model(name)
        except DlaInputError:
            continue
        out.append(name)
    return out


def motion_suite(cfg: SpeedConfig, row, log) -> list[dict]:
    """`dla motion from-video` on a synthetic video of a known motion (data/video.py; the clip
    played forward and backward until `motion_seconds` long, at 30 fps): the whole command in a
    fresh interpreter (one warm-up run; `items` = video frames, so frames per second = items /
    seconds), and in this process its detection and fit (wall seconds) and the process's CPU
    seconds (all threads), which other load on the machine inflates less than wall time."""
    import statistics

    import numpy as np

    from dlacli.data.video import render_motion_video
    from dlacli.io.video import open_video
    from dlacli.limits import DEFAULT_LANDMARKS
    from dlacli.stages.motion.video import video_to_motion
    from dlacli.types import Motion

    clip = _motion_clip(cfg.motion_clip)
    n = max(3, int(round(cfg.motion_seconds * clip.fps)) + 1)
    period = max(1, 2 * (clip.num_frames - 1))
    sel = np.arange(n) % period
    sel = np.where(sel < clip.num_frames, sel, period - sel)  # forward, backward, forward, ...
    clip = Motion(clip.bone_labels, clip.rotations[sel], clip.root_rotation[sel], clip.root_translation[sel], clip.fps)
    base = {"res": cfg.motion_res, "frames": n, "clip": cfg.motion_clip}
    out = []
    with tempfile.TemporaryDirectory(prefix="dla-speed-motion-") as tmp:
        video = Path(tmp) / "clip.mp4"
        render_motion_video(clip, video, res=cfg.motion_res)
        argv = ["motion", "from-video", str(video), "-o", str(Path(tmp) / "m.npz")]
        cli_seconds(argv)  # warm-up
        for landmarks in _installed_landmarks():  # the default's rows first, keyed as before
            c = base if landmarks == DEFAULT_LANDMARKS else {**base, "landmarks": landmarks}
            times = [cli_seconds([*argv, "--landmarks", landmarks])[0] for _ in range(max(1, min(cfg.repeats, 3)))]
            med = statistics.median(times)
            out.append(row("motion", "from_video_command", "cli", c, med, len(times), min_seconds=min(times), items=n))
            log(
                f"motion from-video ({landmarks} landmarks), {n} frames at {cfg.motion_res} px: {med:.1f} s = "
                f"{n / med:.1f} video frames/s"
            )
            parts = []
            for _ in range(max(1, min(cfg.repeats, 3))):
                cpu = time.process_time()
                sec = dict(video_to_motion(open_video(video), landmarks=landmarks).seconds)
                sec["cpu"] = time.process_time() - cpu
                parts.append(sec)
            for stage in ("detect", "fit", "cpu"):
                sec = statistics.median(p[stage] for p in parts)
                case = "from_video_process_cpu" if stage == "cpu" else f"from_video_{stage}"
                out.append(row("motion", case, "cpu", c, sec, len(parts), items=n))
                log(f"motion from-video {stage} ({landmarks}): {sec:.2f} s = {n / sec:.1f} frames/s")
    return out
