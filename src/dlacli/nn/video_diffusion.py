"""The diffusion backend of `dla dream`: a pose-controlled video diffusion model (extra `diffusion`).

The paper's procedure (docs/architecture.md "The method", Dream): render the fitted body's 2D skeleton from cameras
on a 360-degree circle, run a pose-controlled video diffusion model with the photo as reference,
and take evenly spaced frames as the novel views. The model is diffusers' `WanVACEPipeline`
(e.g. Wan2.1-VACE-1.3B): its control video is the skeleton video, frame 0 of which is replaced by
the photo itself and kept (mask 0), so the video starts exactly at the input view; the photo is
also passed as VACE's reference image.

This is the only module that imports diffusers (lazily). Weights are never downloaded: pipelines
load with local_files_only=True, from a local folder or the Hugging Face cache.
"""

from __future__ import annotations

import colorsys
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.geometry import DEPTH_EPS, project_to_cameras
from dlacli.types import Cameras

DEFAULT_MODEL = "Wan-AI/Wan2.1-VACE-1.3B-diffusers"
SUPPORTED = ("WanVACEPipeline",)
PROMPT = (
    "a full-body photo of one person standing still while the camera circles around them, "
    "plain white background, the same person and clothes in every frame, sharp, detailed"
)
NEGATIVE_PROMPT = "blurry, low quality, deformed body, extra limbs, extra people, text, watermark, background clutter"


# ------------------------------------------------------------------------------- skeleton video


def project_points(points: np.ndarray, cameras: Cameras) -> tuple[np.ndarray, np.ndarray]:
    """points [K, 3] world -> (pixels [C, K, 2] (x, y), in_front [C, K] bool) for C cameras
    (float64; pixels of points not in front mean nothing)."""
    px, depth = project_to_cameras(np.asarray(points, np.float64), cameras)
    return px, depth > DEPTH_EPS


def bone_colours(n: int) -> list[tuple[int, int, int]]:
    """n distinct saturated colours (hues around the circle), one per bone, as in pose-ControlNet
    style skeleton images."""
    return [tuple(int(round(255 * c)) for c in colorsys.hsv_to_rgb(i / n, 1.0, 1.0)) for i in range(n)]


def draw_skeletons(
    points: np.ndarray,  # [T, K, 2] pixel positions (x, y)
    visible: np.ndarray,  # [T, K] bool
    bones: tuple[tuple[int, int], ...],
    size: int,
    width: int | None = None,
) -> np.ndarray:
    """Skeleton images [T, size, size, 3] uint8: each bone a coloured line (colour per bone),
    joints as white dots, on black."""
    from PIL import Image, ImageDraw

    width = width or max(1, size // 96)
    colours = bone_colours(len(bones))
    out = np.zeros((points.shape[0], size, size, 3), np.uint8)
    for t in range(points.shape[0]):
        im = Image.new("RGB", (size, size))
        draw = ImageDraw.Draw(im)
        for (a, b), col in zip(bones, colours):
            if visible[t, a] and visible[t, b]:
                draw.line([tuple(points[t, a]), tuple(points[t, b])], fill=col, width=width)
        r = width
        for k in np.nonzero(visible[t])[0]:
            x, y = points[t, k]
            draw.ellipse([x - r, y - r, x + r, y + r], fill=(255, 255, 255))
        out[t] = np.asarray(im)
    return out


# ------------------------------------------------------------------------------- the pipeline


def _diffusers():
    try:
        import diffusers
    except ImportError:
        raise DlaInputError(
            "--backend diffusion", "needs the diffusion extra: pip install 'dla[diffusion]' (or use --backend body)"
        ) from None
    return diffusers


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def default_dtype(device: torch.device) -> torch.dtype:
    """Half precision on CUDA (bfloat16 where supported: Wan and its UMT5 text encoder are trained
    in bfloat16 and UMT5 overflows in float16), float32 on the CPU."""
    if device.type != "cuda":
        return torch.float32
    return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16


def _not_found(model: str) -> DlaInputError:
    hub = model if not os.path.isabs(model) and model.count("/") == 1 else DEFAULT_MODEL
    return DlaInputError(
        "--model",
        f"weights not found at {model} (nothing is downloaded at run time): download {hub} with "
        f"`hf download {hub} --local-dir DIR` (or `huggingface-cli download`) on a machine with "
        "network and pass --model DIR",
    )


def load_pipeline(
    model: str = DEFAULT_MODEL, device: str | torch.device | None = None, dtype: torch.dtype | None = None
):
    """Load a pose-controlled video pipeline from a local folder or the local Hugging Face cache.

    model: a folder written by `save_pretrained` (with model_index.json) or a hub id already in
    the cache. Half precision on CUDA with the VAE kept in float32; on CUDA with accelerate
    installed the pipeline uses model CPU offload (only the active component on the GPU), else
    it is moved to `device`. Raises DlaInputError("--model", ...) when the weights are not there.
    """
    diffusers = _diffusers()
    device = torch.device(device) if device is not None else default_device()
    dtype = dtype or default_dtype(device)
    model = str(model)
    path = Path(model).expanduser()
    if path.exists():
        if not (path / "model_index.json").is_file():
            raise DlaInputError("--model", f"{path} is not a diffusers pipeline folder (no model_index.json)")
        model = str(path)
    elif os.path.isabs(model) or model.startswith((".", "~")) or model.count("/") != 1:
        raise _not_found(model)
    dtypes: Any = {"default": dtype, "vae": torch.float32} if dtype != torch.float32 else dtype
    _quiet_loading(diffusers)
    try:
        pipe = diffusers.DiffusionPipeline.from_pretrained(model, dtype=dtypes, local_files_only=True)
    except (OSError, ValueError) as err:
        if path.exists():
            raise DlaInputError(
                "--model", f"cannot load the pipeline in {path}: {' '.join(str(err).split())[:300]}"
            ) from None
        raise _not_found(model) from None
    name = type(pipe).__name__
    if name not in SUPPORTED:
        raise DlaInputError("--model", f"{model} is a {name}; dla dream needs one of {', '.join(SUPPORTED)}")
    pipe.scheduler = first_order_scheduler(pipe.scheduler)
    if device.type == "cuda" and _has_accelerate():
        pipe.enable_model_cpu_offload(device=device)
    else:
        pipe.to(device)
    pipe.set_progress_bar_config(disable=True)
    return pipe


def _quiet_loading(diffusers) -> None:
    """No tqdm bars from diffusers / transformers while loading (dla shows its own progress)."""
    diffusers.utils.logging.disable_progress_bar()
    try:
        import transformers

        transformers.utils.logging.disable_progress_bar()
    except (ImportError, AttributeError):
        pass


def _has_accelerate() -> bool:
    try:
        import accelerate  # noqa: F401
    except ImportError:
        return False
    return True


def first_order_scheduler(scheduler):
    """The paper samples with DDIM: a deterministic first-order ODE sampler. For a flow-matching
    model (Wan) that is the Euler step of the flow ODE (FlowMatchEulerDiscreteScheduler, with the
    model's timestep shift); for an epsilon/v-prediction model it is DDIMScheduler itself."""
    diffusers = _diffusers()
    cfg = dict(scheduler.config)
    if isinstance(scheduler, (diffusers.FlowMatchEulerDiscreteScheduler, diffusers.DDIMScheduler)):
        return scheduler
    if cfg.get("use_flow_sigmas") or cfg.get("prediction_type") == "flow_prediction":
        shift = float(cfg.get("flow_shift") or cfg.get("shift") or 1.0)
        return diffusers.FlowMatchEulerDiscreteScheduler(
            num_train_timesteps=cfg.get("num_train_timesteps", 1000), shift=shift
        )
    return diffusers.DDIMScheduler.from_config(cfg)


def generate_orbit(
    pipe,
    reference: np.ndarray,  # [H, W, 3] float rgb in [0, 1]: the photo on a white background
    control: np.ndarray,  # [T, H, W, 3] uint8 skeleton frames (frame 0 is replaced by the reference)
    *,
    steps: int = 50,
    seed: int = 0,
    guidance_scale: float = 5.0,
    prompt: str = PROMPT,
    negative_prompt: str = NEGATIVE_PROMPT,
) -> np.ndarray:
    """Run the pipeline: -> frames [T, H, W, 3] float32 rgb in [0, 1].

    Control video: frame 0 = the reference (kept: VACE mask 0), frames 1.. = the skeletons
    (generated: mask 1). T - 1 must be a multiple of the VAE's temporal factor (4 for Wan); H and
    W multiples of 16.
    """
    from PIL import Image

    t, h, w = control.shape[:3]
    if reference.shape != (h, w, 3):
        raise DlaInputError("reference", f"has shape {reference.shape}, expected ({h}, {w}, 3)")
    if h % 16 or w % 16:
        raise DlaInputError("--res", f"{w}x{h}: the diffusion backend needs a multiple of 16")
    ref = Image.fromarray(np.round(np.clip(reference, 0, 1) * 255).astype(np.uint8))
    video = [ref] + [Image.fromarray(f) for f in control[1:]]
    mask = [Image.new("L", (w, h), 0)] + [Image.new("L", (w, h), 255) for _ in range(t - 1)]
    gen = torch.Generator(device="cpu").manual_seed(int(seed))
    with torch.inference_mode():
        out = pipe(
            prompt=prompt,
            negative_prompt=negative_prompt,
            video=video,
            mask=mask,
            reference_images=[ref],
            height=h,
            width=w,
            num_frames=t,
            num_inference_steps=int(steps),
            guidance_scale=float(guidance_scale),
            generator=gen,
            output_type="np",
        )
    frames = np.asarray(out.frames[0], dtype=np.float32)  # [T, H, W, 3]
    if frames.shape != (t, h, w, 3):
        raise RuntimeError(f"the pipeline returned frames of shape {frames.shape}, expected {(t, h, w, 3)}")
    return np.clip(frames, 0.0, 1.0)
