"""The diffusion backend of dla dream, end to end on a tiny randomly initialised WanVACEPipeline
(a few channels and layers, random weights, saved with save_pretrained and loaded back with
load_pipeline); no real weights are needed or downloaded. Skipped without diffusers."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

pytest.importorskip("diffusers")
pytest.importorskip("transformers")
pytest.importorskip("ftfy")  # the Wan pipelines clean prompts with ftfy

from dlacli.errors import DlaInputError  # noqa: E402
from dlacli.types import BodyParams, Cameras  # noqa: E402

RES = 32
FRAMES = 8  # the paper's 80 would be 81 video frames; 8 -> 9 (Wan needs 4 k + 1)


def _tiny_pipeline(folder):
    """Tiny WanVACEPipeline: word-level tokenizer, 1-layer UMT5, 4-channel VAE, 2-layer VACE
    transformer; the scheduler is Wan's UniPC flow config (load_pipeline swaps in Euler)."""
    from diffusers import AutoencoderKLWan, UniPCMultistepScheduler, WanVACEPipeline, WanVACETransformer3DModel
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast, UMT5Config, UMT5EncoderModel

    torch.manual_seed(0)
    words = ["[PAD]", "[UNK]", "</s>", "a", "person", "photo", "white", "background"]
    tok = Tokenizer(models.WordLevel({w: i for i, w in enumerate(words)}, unk_token="[UNK]"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tokenizer = PreTrainedTokenizerFast(tokenizer_object=tok, pad_token="[PAD]", unk_token="[UNK]", eos_token="</s>")
    cfg = UMT5Config(
        vocab_size=len(words), d_model=16, d_kv=8, d_ff=32, num_layers=1, num_heads=2, relative_attention_num_buckets=8
    )
    text_encoder = UMT5EncoderModel(cfg).eval()
    z = 4
    vae = AutoencoderKLWan(
        base_dim=8,
        z_dim=z,
        dim_mult=[1, 1, 1, 1],
        num_res_blocks=1,
        temperal_downsample=[False, True, True],
        latents_mean=[0.0] * z,
        latents_std=[1.0] * z,
    )
    transformer = WanVACETransformer3DModel(
        patch_size=(1, 2, 2),
        num_attention_heads=2,
        attention_head_dim=8,
        in_channels=z,
        out_channels=z,
        text_dim=16,
        freq_dim=32,
        ffn_dim=32,
        num_layers=2,
        rope_max_seq_len=32,
        vace_layers=[0, 1],
        vace_in_channels=2 * z + 64,  # inactive + reactive latents + the 8 x 8 packed mask
    )
    scheduler = UniPCMultistepScheduler(prediction_type="flow_prediction", use_flow_sigmas=True, flow_shift=3.0)
    pipe = WanVACEPipeline(
        tokenizer=tokenizer, text_encoder=text_encoder, vae=vae, scheduler=scheduler, transformer=transformer
    )
    pipe.save_pretrained(folder)
    return pipe


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_wan_vace")
    original = _tiny_pipeline(folder)
    return folder, original


@pytest.fixture(scope="module")
def subject():
    """A posed body "photo" (known camera) and its true fit, as in tests/stages/test_dream.py."""
    from dlacli.body.keypoints import coco_keypoints
    from dlacli.body.model import get_body_model
    from dlacli.render.raster import render_mesh
    from dlacli.stages.fit.photo import FitResult

    m = get_body_model()
    body = BodyParams()
    verts = m.forward_body(body).vertices[0].numpy()
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = [1, 0, 0], [0, 0, 1], [0, -1, 0], [0, -3, -0.1]
    cam = Cameras.from_c2w_opengl(c2w[None], 220.0, 220.0, 64.0, 96.0, 128, 192)
    rgba = render_mesh(verts, m.faces, np.full((verts.shape[0], 3), 0.6), cam)[0]
    kp = np.concatenate([np.zeros((17, 2)), np.ones((17, 1))], 1)  # unused by the views
    fit = FitResult(body, cam, verts, kp, 0.0, 1.0)
    assert coco_keypoints(verts).shape == (17, 3)
    return rgba[..., :3] / np.maximum(rgba[..., 3:], 1e-6), rgba[..., 3], fit


def test_load_pipeline_round_trip(tiny):
    """The saved pipeline loads back with the same weights, in float32 on the CPU, with the
    DDIM-like first-order sampler (Euler on the flow ODE, the model's shift)."""
    from diffusers import FlowMatchEulerDiscreteScheduler

    from dlacli.nn.video_diffusion import load_pipeline

    folder, original = tiny
    pipe = load_pipeline(str(folder), device="cpu")
    assert type(pipe).__name__ == "WanVACEPipeline"
    assert isinstance(pipe.scheduler, FlowMatchEulerDiscreteScheduler) and pipe.scheduler.config.shift == 3.0
    for name in ("transformer", "vae", "text_encoder"):
        a, b = getattr(pipe, name).state_dict(), getattr(original, name).state_dict()
        assert a.keys() == b.keys()
        for key in a:
            assert a[key].dtype == torch.float32
            torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)


def test_missing_weights_name_model():
    from dlacli.nn.video_diffusion import DEFAULT_MODEL, load_pipeline

    for model in (DEFAULT_MODEL, "someone/not-cached-anywhere", "/no/such/folder"):
        with pytest.raises(DlaInputError, match="--model") as err:
            load_pipeline(model, device="cpu")
        assert "weights not found" in str(err.value) and "download" in str(err.value)


def test_folder_without_model_index(tmp_path):
    from dlacli.nn.video_diffusion import load_pipeline

    with pytest.raises(DlaInputError, match="model_index.json"):
        load_pipeline(str(tmp_path), device="cpu")


def test_first_order_scheduler():
    from diffusers import DDIMScheduler, DDPMScheduler, FlowMatchEulerDiscreteScheduler, UniPCMultistepScheduler

    from dlacli.nn.video_diffusion import first_order_scheduler

    flow = first_order_scheduler(
        UniPCMultistepScheduler(prediction_type="flow_prediction", use_flow_sigmas=True, flow_shift=5.0)
    )
    assert isinstance(flow, FlowMatchEulerDiscreteScheduler) and flow.config.shift == 5.0
    eps = first_order_scheduler(DDPMScheduler(beta_schedule="scaled_linear"))
    assert isinstance(eps, DDIMScheduler) and eps.config.beta_schedule == "scaled_linear"


def test_draw_skeletons_lines_and_joints():
    from dlacli.nn.video_diffusion import bone_colours, draw_skeletons

    pts = np.array([[[4.0, 10.5], [28.0, 10.5], [16.0, 28.5]]])  # [1, 3, 2]
    vis = np.array([[True, True, False]])
    img = draw_skeletons(pts, vis, ((0, 1), (1, 2)), 32, width=1)[0]
    colour = bone_colours(2)[0]
    assert tuple(img[10, 16]) == colour  # the middle of bone 0
    assert tuple(img[10, 4]) == (255, 255, 255)  # a joint
    assert img[20:, :].max() == 0  # bone 1 ends at an invisible joint: not drawn


def test_orbit_skeleton_turns_around(subject):
    """Orbit frames: at frame 0 the person's left shoulder (+X) is on the image right; at the
    half-way frame (azimuth 180) it is on the left; at N/4 (camera on +X) it is nearer."""
    from dlacli.body.keypoints import coco_keypoints
    from dlacli.nn.video_diffusion import project_points
    from dlacli.stages.dream.backends.diffusion import orbit_frame_azimuths, view_frames
    from dlacli.stages.dream.orbit import body_pivot, orbit_cameras

    _, _, fit = subject
    az = orbit_frame_azimuths(80)
    assert [az[i] for i in view_frames(80)] == [90.0, 180.0, 270.0] and az[80] == 360.0 and len(az) == 81
    cams = orbit_cameras(fit.camera, body_pivot(fit.vertices), az)
    kp = coco_keypoints(fit.vertices.astype(np.float64))
    px, front = project_points(kp, cams)
    assert front.all()
    ls, rs = 5, 6  # COCO left / right shoulder
    assert px[0, ls, 0] > px[0, rs, 0] and px[40, ls, 0] < px[40, rs, 0]
    depth = (
        np.einsum("ij,kj->ki", cams.viewmats[20, :3, :3].double().numpy(), kp)[:, 2] + cams.viewmats[20, 2, 3].item()
    )
    assert depth[ls] < depth[rs]


def test_dream_diffusion_end_to_end(tiny, subject, tmp_path):
    """build_views with the tiny pipeline (2 steps, 9 frames, 32 x 32) -> a view folder that
    reads back; view 0 is the photo, the others come from the video frames N/4, N/2, 3N/4."""
    from dlacli.io.views import read_views
    from dlacli.nn.video_diffusion import load_pipeline
    from dlacli.stages.dream.views import build_views, frame_crop, write_dream_folder

    folder, _ = tiny
    rgb, alpha, fit = subject
    pipe = load_pipeline(str(folder), device="cpu")
    views = build_views(rgb, alpha, fit, backend="diffusion", res=RES, pipe=pipe, frames=FRAMES, steps=2)
    out = write_dream_folder(views, np.zeros((4, 4, 3), np.uint8), tmp_path / "views")
    vs = read_views(out)
    assert vs.images.shape == (4, RES, RES, 3) and np.all(vs.masks.reshape(4, -1).max(1) > 0)
    meta = json.loads((out / "transforms.json").read_text())["dla"]["dream"]
    assert meta["backend"] == "diffusion" and meta["video_frames"] == [0, 2, 4, 6] and meta["steps"] == 2
    crop_rgb, crop_alpha, _ = frame_crop(rgb, alpha, fit.camera, RES)
    np.testing.assert_allclose(vs.masks[0], np.round(crop_alpha * 255) / 255, atol=1e-6)


def test_dla_dream_diffusion_cli(tiny, third_party_data, tmp_path):
    """`dla dream --backend diffusion --model <tiny folder>` on a real photo (a 3-step fit, 5
    video frames, 2 sampling steps, 64 x 64) writes a view folder that reads back."""
    from pathlib import Path

    from typer.testing import CliRunner

    from dlacli.cli.app import app
    from dlacli.io.views import read_views

    stem = "pexels-photo-6311555-removebg"
    photo = third_party_data / "images" / f"{stem}.png"
    kp = Path(__file__).resolve().parent.parent / "data" / "keypoints" / f"{stem}.json"
    if not kp.is_file():
        pytest.skip(f"missing keypoints {kp}")
    folder, _ = tiny
    out = tmp_path / "views"
    args = [
        "dream",
        str(photo),
        "-o",
        str(out),
        "--backend",
        "diffusion",
        "--model",
        str(folder),
        "--keypoints",
        str(kp),
        "--res",
        "64",
        "--frames",
        "4",
        "--steps",
        "2",
        "--fit-steps",
        "3",
    ]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    vs = read_views(out)
    assert vs.images.shape == (4, 64, 64, 3)
    meta = json.loads((out / "transforms.json").read_text())["dla"]["dream"]
    assert meta["video_frames"] == [0, 1, 2, 3] and meta["model"] == str(folder)
    bad = CliRunner().invoke(app, args[:6] + ["--model", str(tmp_path / "nothing")] + args[8:])
    assert isinstance(bad.exception, DlaInputError) and "--model" in str(bad.exception)
