"""`dla view`: the page is one self-contained file whose embedded data decodes back to the rig
(within the stated quantisation), and headless Chromium's WebGL2 rendering of it matches the CPU
splatter's image of the same Gaussians, frame and camera (docs/view.md).

The browser tests need the Debian package `chromium` (SwiftShader's software WebGL2 ships in
it); without it they are skipped.
"""

from __future__ import annotations

import base64
import gzip
import json
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dlacli.bench.browser import DevToolsPage, chromium, chromium_command, time_page
from dlacli.cli.app import main

N = 4096
FRAME = 40  # a walk frame well into the stride (the built-in walk has more frames)
WIDTH, HEIGHT = 256, 192
INTRINSICS = (240.0, 250.0, 121.5, 101.0)  # fx, fy, cx, cy: non-square pixels, off-centre principal point
CHROMIUM = chromium()
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="headless Chromium not installed (Debian: apt-get install chromium)"
)


def run(argv, capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as info:
        main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return info.value.code, out, err


@pytest.fixture(scope="module")
def avatar_path(tmp_path_factory):
    """A small lifted avatar (synthetic subject, unprojection only, N Gaussians)."""
    from dlacli.data.synth import synth
    from dlacli.io.avatar import write_avatar
    from dlacli.io.views import read_views
    from dlacli.stages.lift.methods.unproject import UnprojectConfig
    from dlacli.stages.lift.unproject import lift

    root = tmp_path_factory.mktemp("view")
    views = synth(5, root / "s5", res=96, novel_views=0, novel_poses=0)
    write_avatar(lift(read_views(views), UnprojectConfig(steps=0, gaussians=N)).avatar, root / "avatar.npz")
    return root / "avatar.npz"


@pytest.fixture(scope="module")
def page(avatar_path):
    out = avatar_path.with_name("walk.html")
    with pytest.raises(SystemExit) as info:
        main(["view", str(avatar_path), "--motion", "walk", "-o", str(out)])
    assert info.value.code == 0
    return out


@pytest.fixture(scope="module")
def reference(avatar_path):
    """The rig and joint matrices the page should hold (built independently of the page)."""
    from dlacli.io.avatar import read_avatar
    from dlacli.stages.motion.source import load_motion
    from dlacli.stages.rig import build_rig, skinning_matrices

    av = read_avatar(avatar_path)
    motion = load_motion("walk", phenotype=av.body.phenotype)
    return build_rig(av), skinning_matrices(av, motion), motion


class _Scripts(HTMLParser):
    """Text of every <script> element by id ("" for those without), and their src attributes."""

    def __init__(self):
        super().__init__()
        self.text, self.srcs, self._id = {}, [], None

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "script":
            self._id = attrs.get("id", "")
            self.text.setdefault(self._id, "")
            if "src" in attrs:
                self.srcs.append(attrs["src"])

    def handle_endtag(self, tag):
        if tag == "script":
            self._id = None

    def handle_data(self, data):
        if self._id is not None:
            self.text[self._id] += data


def decode_page(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The page's header and its arrays, decoded here from the format the header states."""
    parser = _Scripts()
    parser.feed(path.read_text(encoding="utf-8"))
    meta = json.loads(parser.text["dla-meta"])
    raw = gzip.decompress(base64.b64decode(parser.text["dla-data"].strip()))
    dtypes = {"u8": "<u1", "u16": "<u2", "i16": "<i2", "f16": "<f2", "f32": "<f4"}
    arrays = {}
    for name, spec in meta["arrays"].items():
        count = int(np.prod(spec["shape"]))
        arrays[name] = np.frombuffer(raw, dtypes[spec["dtype"]], count, spec["offset"]).reshape(spec["shape"])
    return meta, arrays


def test_page_is_self_contained(page):
    parser = _Scripts()
    text = page.read_text(encoding="utf-8")
    parser.feed(text)
    assert parser.srcs == []  # no external scripts
    assert "http://" not in text and "https://" not in text
    assert "default-src 'none'" in text  # CSP: the page may not fetch anything
    assert {"dla-meta", "dla-data", ""} <= set(parser.text)


def test_embedded_data_decodes_to_the_rig(page, reference):
    rig, mats, motion = reference
    meta, a = decode_page(page)
    assert meta["format"] == "dla.view/1" and meta["gaussians"] == len(rig) == N
    assert meta["frames"] == motion.num_frames and meta["fps"] == motion.fps
    # positions: u16 on the bounding box, error <= step / 2 (+ float32 rounding of the decode)
    lo, step = np.array(meta["position_min"]), np.array(meta["position_step"])
    pos = lo + a["positions"] * step
    assert np.all(np.abs(pos - rig.positions) <= step / 2 + 4 * np.finfo(np.float32).eps)
    # quaternions: int16 = round(32767 q); per component 0.5 / 32767, x2 for the renormalisation
    q = a["quats"] / 32767.0
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    sign = np.sign(np.sum(q * rig.quats, axis=1, keepdims=True))
    assert np.abs(q * sign - rig.quats).max() <= 1.0 / 32767
    # scales: float16, relative 2^-11 in its normal range, absolute 2^-25 below (subnormals)
    s = a["scales"].astype(np.float64)
    assert np.all(np.abs(s - rig.scales) <= np.maximum(2.0**-11 * rig.scales, 2.0**-25))
    # opacities and colours: u8, error <= 1/510
    assert np.abs(a["opacities"] / 255.0 - rig.opacities).max() <= 0.5 / 255 + 1e-7
    assert np.abs(a["rgb"] / 255.0 - rig.rgb).max() <= 0.5 / 255 + 1e-7
    # weights: integers summing to 255 per row, each within one unit of the rig's weight
    scale = meta["weight_scale"]
    assert scale == 255 and np.all(a["joint_weights"].sum(axis=1, dtype=np.int64) == scale)
    joints = [rig.joint_names.index(name) for name in meta["joint_names"]]
    dense_page = np.zeros((N, rig.num_joints))
    dense_rig = np.zeros((N, rig.num_joints))
    rows = np.arange(N)[:, None]
    np.add.at(dense_page, (rows, np.array(joints)[a["joint_indices"]]), a["joint_weights"] / scale)
    np.add.at(dense_rig, (rows, rig.joint_indices), rig.joint_weights)
    assert np.abs(dense_page - dense_rig).max() < 1.0 / scale
    # matrices: float32, exactly the rig's (top three rows) for the joints kept
    assert np.array_equal(a["matrices"], mats[:, joints, :3, :])
    assert np.all(dense_rig[:, np.setdiff1d(np.arange(rig.num_joints), joints)] == 0)


def test_page_without_motion_holds_the_avatars_own_pose(avatar_path, capsys):
    """No --motion: one frame, the pose of the avatar's body.json (what `dla render` shows)."""
    import torch

    from dlacli.body.model import get_body_model
    from dlacli.io.avatar import read_avatar

    code, out, err = run(["view", avatar_path, "--gaussians", 64], capsys)
    assert code == 0, err
    page = avatar_path.with_suffix(".html")  # the default output
    assert out.strip() == str(page)
    meta, a = decode_page(page)
    assert meta["frames"] == 1 and meta["gaussians"] == 64
    model = get_body_model()
    body = read_avatar(avatar_path).body
    posed = model.forward_body(body).bone_transforms[0].double()
    rest = model.zero_pose(body.phenotype).bone_transforms[0].double()
    want = (posed @ torch.linalg.inv(rest)).numpy()  # world from rest, per joint
    joints = [model.bone_labels.index(name) for name in meta["joint_names"]]
    # float32 storage of matrices with entries up to ~1 m: a few float32 steps
    np.testing.assert_allclose(a["matrices"][0], want[joints, :3, :], atol=1e-6)


def test_bad_input_is_one_line(avatar_path, tmp_path, capsys):
    for argv, words in (
        (["view", avatar_path, "-o", tmp_path / "v.usdc"], ("v.usdc", ".html")),
        (["view", avatar_path, "--motion", "moonwalk", "-o", tmp_path / "v.html"], ("moonwalk", "built-in")),
        (["view", avatar_path, "--fps", "10", "-o", tmp_path / "v.html"], ("--fps", "--motion")),
        (["view", tmp_path / "missing.npz", "-o", tmp_path / "v.html"], ("missing.npz",)),
    ):
        code, _, err = run(argv, capsys)
        assert code == 2 and err.startswith("error: ") and len(err.strip().splitlines()) == 1, err
        assert all(w in err for w in words), err
    assert list(tmp_path.iterdir()) == []


def _camera(positions: np.ndarray):
    """A dla camera (OpenCV axes) looking at the Gaussians from a three-quarter view."""
    import torch

    from dlacli.geometry import look_at_c2w, orbit_eyes
    from dlacli.types import Cameras

    target = 0.5 * (positions.min(axis=0) + positions.max(axis=0))
    c2w = look_at_c2w(orbit_eyes(target, 2.3, 35.0, 10.0), target)
    fx, fy, cx, cy = INTRINSICS
    cams = Cameras.from_c2w_opengl(c2w, fx, fy, cx, cy, WIDTH, HEIGHT)
    return Cameras(
        cams.viewmats.double().float(),
        torch.tensor([[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]], dtype=torch.float32),
        WIDTH,
        HEIGHT,
    )


def _chromium(url: str, tmp: Path, *action: str, budget_ms: int = 30000) -> subprocess.CompletedProcess:
    """One headless Chromium run (software WebGL2 through SwiftShader), e.g. --dump-dom or
    --screenshot=PNG, after `budget_ms` of virtual time."""
    cmd = chromium_command(url, tmp / "profile", WIDTH, HEIGHT, *action, budget_ms=budget_ms)
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    return result


def _screenshot(url: str, tmp: Path, name: str, budget_ms: int = 30000) -> np.ndarray:
    png = tmp / f"{name}.png"
    _chromium(url, tmp, f"--screenshot={png}", budget_ms=budget_ms)
    return np.asarray(Image.open(png).convert("RGB"))


def _cpu_render(rig, mats: np.ndarray, frame: int, cams, background: float) -> tuple[np.ndarray, np.ndarray]:
    """The reference: the rig skinned by `dlacli.stages.rig.skin` at `frame`, splatted by the CPU
    renderer -> 8-bit rgb [H, W, 3] (as the page shows it) and alpha [H, W]."""
    import torch

    from dlacli.render.splat import render_gaussians
    from dlacli.stages.rig import skin
    from dlacli.types import Gaussians

    pos, quats = skin(rig, mats[frame])
    g = Gaussians.from_rgb(*(torch.from_numpy(x) for x in (pos, quats, rig.scales, rig.opacities, rig.rgb)))
    with torch.no_grad():
        out = render_gaussians(g, cams, background=torch.full((3,), float(background)))
    return np.rint(out.rgb[0].clamp(0, 1).numpy() * 255).astype(np.uint8), out.alpha[0].numpy()


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    mse = np.mean(((a.astype(np.float64) - b) / 255.0)[mask] ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))


def _url(page: Path, cams, **params) -> str:
    """The page at a dla camera (viewmat row-major, OpenCV axes) and other hash parameters."""
    view = ",".join(repr(float(x)) for x in cams.viewmats[0].double().numpy().reshape(-1))
    intrinsics = ",".join(repr(float(x)) for x in INTRINSICS)
    extra = "".join(f"&{k}={v}" for k, v in params.items())
    return f"file://{page}#ui=0&size={WIDTH},{HEIGHT}&viewmat={view}&intrinsics={intrinsics}{extra}"


# Floors, from the differences expected between the page and the CPU splatter (measured here:
# PSNR ~52 dB over the body's pixels, mask IoU ~0.9997): both images are rounded to 8 bits
# (<= 0.5 level each); the page blends in float16 (11-bit mantissa per layer); its data are
# quantised (means ~15 um, u8 weights <= 0.4 mm, float16 sigmas), so Gaussians whose depths lie
# closer than that can be drawn in the other order (a few pixels off by tens of levels); one
# global back-to-front order by centre depth (16-bit keys) instead of the CPU's per-tile lists;
# fringe pixels beyond the CPU's 3-sigma tile rectangle (<= opacity exp(-4.5) ~ 0.011 each) and
# its early stop (T <= 1e-4). 40 dB is an RMS error of 2.5 levels; a wrong camera convention,
# frame, colour or skinning costs far more (frame 0 against the last frame: < 20 dB).
PSNR_FLOOR = 40.0
IOU_FLOOR = 0.98


@needs_chromium
def test_browser_render_matches_the_cpu_splatter(page, reference, tmp_path):
    from dlacli.stages.rig import skin

    rig, mats, _ = reference
    cams = _camera(skin(rig, mats[FRAME])[0])
    dom = _chromium(_url(page, cams, frame=FRAME), tmp_path, "--dump-dom").stdout
    assert f'data-dla-ready="{FRAME}"' in dom and "data-dla-error" not in dom, dom[:300]
    shots, refs, alpha_cpu = {}, {}, None
    for name, bg in (("black", 0), ("white", 1)):
        shots[name] = _screenshot(_url(page, cams, frame=FRAME, background=f"{bg},{bg},{bg}"), tmp_path, name)
        refs[name], alpha_cpu = _cpu_render(rig, mats, FRAME, cams, bg)
    assert shots["black"].shape == (HEIGHT, WIDTH, 3)
    # the person's pixels: alpha from the two backgrounds (white - black = 1 - alpha)
    alpha_web = 1.0 - (shots["white"].astype(np.float64) - shots["black"]).mean(axis=2) / 255.0
    covered = (alpha_cpu > 1 / 255) | (alpha_web > 1.5 / 255)
    iou = np.sum((alpha_cpu > 0.5) & (alpha_web > 0.5)) / np.sum((alpha_cpu > 0.5) | (alpha_web > 0.5))
    psnr = {name: _psnr(shots[name], refs[name], covered) for name in shots}
    side = np.concatenate(
        [
            np.concatenate(
                [refs[n], shots[n], np.clip(8 * np.abs(refs[n].astype(int) - shots[n]), 0, 255).astype(np.uint8)], 1
            )
            for n in ("black", "white")
        ],
        0,
    )
    Image.fromarray(side).save(tmp_path / "side_by_side.png")  # CPU | browser | 8x |difference|
    print(
        f"view vs CPU: PSNR {psnr} dB over {covered.sum()} px, mask IoU {iou:.4f}, side by side: "
        f"{tmp_path / 'side_by_side.png'}"
    )
    assert covered.sum() > 0.05 * WIDTH * HEIGHT  # the body is in the picture
    assert min(psnr.values()) > PSNR_FLOOR, psnr
    assert iou > IOU_FLOOR, iou


@needs_chromium
def test_page_plays_and_the_js_hook_places_the_camera(page, reference, tmp_path):
    """window.dlaView: play() steps through frames by itself, pause() holds one, setView() puts
    the camera at a dla camera; the paused frame then matches the CPU splatter's image of it."""
    from dlacli.stages.rig import skin

    rig, mats, motion = reference
    chrome = DevToolsPage(tmp_path / "devtools-profile", WIDTH, HEIGHT)
    try:
        chrome.send("Page.navigate", {"url": f"file://{page}#ui=0&background=0,0,0&frame=0"})
        chrome.wait_for("window.dlaReady === true")
        assert chrome.js("document.documentElement.dataset.dlaError || ''") == ""
        chrome.js("window.dlaView.play()")
        first = chrome.wait_for("window.dlaView.state().frame")  # > 0: playing moved on
        second = chrome.wait_for(f"window.dlaView.state().frame !== {first} && window.dlaView.state().frame")
        assert second != first
        chrome.js("window.dlaView.pause()")
        frame = chrome.js("window.dlaView.state().frame")
        assert 0 <= frame < motion.num_frames and chrome.js("window.dlaView.state().playing") is False
        # aimed at the body in the paused frame: how far play got depends on the machine's load,
        # and a walk leaves a camera aimed at frame 0
        cams = _camera(skin(rig, mats[frame])[0])
        fx, fy, cx, cy = INTRINSICS
        view = json.dumps(cams.viewmats[0].double().numpy().tolist())
        state = chrome.js(
            f"window.dlaView.setView({{viewmat: {view}, fx: {fx}, fy: {fy}, cx: {cx}, cy: {cy}, "
            f"width: {WIDTH}, height: {HEIGHT}}})"
        )
        assert state["frame"] == frame  # setView without a frame keeps the paused one
        shot = chrome.screenshot()
    finally:
        chrome.close()
    ref, alpha = _cpu_render(rig, mats, frame, cams, 0)
    covered = alpha > 1 / 255
    assert shot.shape == (HEIGHT, WIDTH, 3)
    psnr = _psnr(shot, ref, covered)
    print(f"paused at frame {frame}: PSNR {psnr:.2f} dB against the CPU splatter")
    assert psnr > PSNR_FLOOR


@needs_chromium
def test_page_times_its_frames_and_keeps_its_frame(page, reference, tmp_path):
    """dlaView.timeFrames(N) (what `dla bench speed --suite view` reads): the page draws N
    successive frames, reports its frames per second and the JS / GL split, and comes back to the
    frame it showed."""
    frames = 12
    t = time_page(page, WIDTH, HEIGHT, frames, tmp_path / "profile")
    assert np.isfinite(t["fps"]) and t["fps"] > 0
    assert t["js_ms"] >= 0 and t["gl_ms"] >= 0
    assert t["frame"] == 0  # the page shows frame 0 again
