"""Image losses shared by optimisation (lift refinement), training and metrics.

Images are [..., H, W, C] float tensors in [0, 1] (channels last, as the renderers return them).
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as nnf

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
_C1, _C2 = 0.01**2, 0.03**2  # (K1 L)^2, (K2 L)^2 with L = 1


@functools.lru_cache(maxsize=8)
def _gauss_1d(size: int, sigma: float, dtype: torch.dtype, device: str) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of [B, C, H, W] with 'valid' borders."""
    c = x.shape[1]
    x = nnf.conv2d(x, g.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return nnf.conv2d(x, g.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def ssim_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM (Wang et al. 2004: 11x11 Gaussian window, sigma 1.5, K1 0.01, K2 0.03,
    'valid' borders) of images [..., H, W, C] -> [..., H - 10, W - 10, C]."""
    if a.shape != b.shape:
        raise ValueError(f"ssim: shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    lead = a.shape[:-3]
    h, w, c = a.shape[-3:]
    x = a.reshape(-1, h, w, c).permute(0, 3, 1, 2)
    y = b.reshape(-1, h, w, c).permute(0, 3, 1, 2)
    g = _gauss_1d(min(SSIM_WINDOW, h, w) | 1, SSIM_SIGMA, a.dtype, str(a.device))
    mx, my = _blur(x, g), _blur(y, g)
    sxx = _blur(x * x, g) - mx * mx
    syy = _blur(y * y, g) - my * my
    sxy = _blur(x * y, g) - mx * my
    s = ((2 * mx * my + _C1) * (2 * sxy + _C2)) / ((mx * mx + my * my + _C1) * (sxx + syy + _C2))
    return s.permute(0, 2, 3, 1).reshape(*lead, s.shape[2], s.shape[3], c)


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of images [..., H, W, C] (a scalar tensor; differentiable)."""
    return ssim_map(a, b).mean()


# ---------------------------------------------------------------------------- perceptual loss
#
# The paper's perceptual term compares AlexNet features of the render and the ground truth inside
# the person's mask (LPIPS-style). AlexNet's weights are not shipped and nothing may download
# them, so the term has two forms:
#   "alexnet"  when the user supplies torchvision-layout AlexNet weights locally (`load_alexnet`);
#   "ms-ssim"  otherwise: 1 - multi-scale SSIM (Wang, Simoncelli & Bovik 2003) inside the mask.
# Why MS-SSIM: what a feature-space loss adds over L1 is structure at several scales (edges,
# texture contrast) rather than per-pixel agreement; SSIM's contrast and structure terms compare
# exactly that per window, and at 3 scales (full, 1/2, 1/4) the windows span 11 to 44 pixels.
# It needs no weights, is differentiable and bounded, and L1 + MS-SSIM is a standard image
# restoration loss (Zhao et al. 2017, "Loss Functions for Image Restoration with Neural Networks").

MS_SSIM_SCALES = 3


def _nchw(x: torch.Tensor) -> torch.Tensor:
    h, w, c = x.shape[-3:]
    return x.reshape(-1, h, w, c).permute(0, 3, 1, 2)


def _masked_mean(values: torch.Tensor, weight: torch.Tensor | None) -> torch.Tensor | None:
    """Mean of values [B, C, H, W] weighted by weight [B, 1, H, W] (plain mean for None; None
    when the weights are all zero)."""
    if weight is None:
        return values.mean()
    w = weight.expand_as(values)
    total = w.sum()
    return (values * w).sum() / total if float(total) > 0 else None


def _window_crop(x: torch.Tensor, size: int) -> torch.Tensor:
    """The pixels of [B, C, H, W] that are centres of 'valid' size x size windows."""
    lo = (size - 1) // 2
    hi = size - 1 - lo
    return x[..., lo : x.shape[-2] - hi, lo : x.shape[-1] - hi]


def ms_ssim_loss(
    pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None, scales: int = MS_SSIM_SCALES
) -> torch.Tensor:
    """1 - mean over `scales` dyadic scales of the SSIM map (11x11 Gaussian window) of images
    [..., H, W, C], averaged inside mask [..., H, W] (weights in [0, 1]; None: everywhere).
    Scales whose image is smaller than the window, or where no window centre is inside the mask,
    are skipped; with none left the loss is 0."""
    x, y = _nchw(pred), _nchw(gt)
    m = None if mask is None else mask.reshape(-1, 1, *mask.shape[-2:]).to(x.dtype)
    terms = []
    for s in range(scales):
        if s and min(x.shape[-2:]) < SSIM_WINDOW:
            break
        size = min(SSIM_WINDOW, x.shape[-2], x.shape[-1]) | 1
        smap = ssim_map(x.permute(0, 2, 3, 1), y.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)
        term = _masked_mean(smap, None if m is None else _window_crop(m, size))
        if term is not None:
            terms.append(term)
        x, y = nnf.avg_pool2d(x, 2), nnf.avg_pool2d(y, 2)
        m = None if m is None else nnf.avg_pool2d(m, 2)
    if not terms:
        return 0.0 * pred.sum()
    return 1.0 - torch.stack(terms).mean()


class AlexNetFeatures(torch.nn.Module):
    """AlexNet's convolutional trunk in torchvision's layout (`features.0` ... `features.10`),
    returning the five ReLU outputs LPIPS compares. Weights come only from a local file."""

    RELU_AFTER = (1, 4, 7, 9, 11)  # indices in `features` whose outputs are compared

    def __init__(self):
        super().__init__()
        nn = torch.nn
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, 11, stride=4, padding=2),
            nn.ReLU(),
            nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2),
            nn.ReLU(),
            nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(384, 256, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(256, 256, 3, padding=1),
            nn.ReLU(),
        )
        # ImageNet normalisation of inputs in [0, 1]
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """x [B, 3, H, W] in [0, 1] -> the five ReLU feature maps."""
        out, h = [], (x - self.mean) / self.std
        for i, layer in enumerate(self.features):
            h = layer(h)
            if i in self.RELU_AFTER:
                out.append(h)
        return out


def load_alexnet(path) -> AlexNetFeatures:
    """AlexNet features from a local weights file: safetensors, or a torch state dict (.pth, read
    with weights_only=True: no code runs). Keys as torchvision's `alexnet().state_dict()`
    (`features.N.weight`; the classifier's keys are ignored) or without the `features.` prefix."""
    from pathlib import Path

    from dlacli.errors import DlaInputError

    p = Path(path)
    if not p.is_file():
        raise DlaInputError(p, "AlexNet weights: no such file")
    try:
        if p.suffix.lower() == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(p))
        else:
            state = torch.load(str(p), map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unreadable file is a user error
        raise DlaInputError(p, f"AlexNet weights: cannot read ({type(err).__name__})") from None
    if not isinstance(state, dict):
        raise DlaInputError(p, "AlexNet weights: not a state dict")
    net = AlexNetFeatures()
    want = net.state_dict()
    got = {}
    for key in want:
        short = key.removeprefix("features.")
        t = state.get(key, state.get(short))
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != tuple(want[key].shape):
            raise DlaInputError(p, f"AlexNet weights: {key} missing or of the wrong shape")
        got[key] = t.float()
    net.load_state_dict(got)
    net.eval().requires_grad_(False)
    return net


def alexnet_loss(
    net: AlexNetFeatures, pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """LPIPS-style distance without learned layer weights: at each of AlexNet's five ReLU outputs,
    features are unit-normalised over channels, squared differences summed over channels and
    averaged over the feature map inside the (area-resized) mask; the five layers are summed.
    Images [..., H, W, 3] in [0, 1], mask [..., H, W]."""
    x, y = _nchw(pred), _nchw(gt)
    fx, fy = net(x), net(y)
    m = None if mask is None else mask.reshape(-1, 1, *mask.shape[-2:]).to(x.dtype)
    total = x.new_zeros(())
    for a, b in zip(fx, fy):
        a = a / a.norm(dim=1, keepdim=True).clamp_min(1e-10)
        b = b / b.norm(dim=1, keepdim=True).clamp_min(1e-10)
        d = ((a - b) ** 2).sum(dim=1, keepdim=True)
        w = None if m is None else nnf.adaptive_avg_pool2d(m, d.shape[-2:])
        term = _masked_mean(d, w)
        total = total + (term if term is not None else 0.0)
    return total


def perceptual_loss(
    pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None, alexnet: AlexNetFeatures | None = None
) -> torch.Tensor:
    """The training's perceptual term: `alexnet_loss` when AlexNet weights were supplied,
    otherwise the weights-free `ms_ssim_loss` (see the section comment above)."""
    if alexnet is not None:
        return alexnet_loss(alexnet, pred, gt, mask)
    return ms_ssim_loss(pred, gt, mask)
