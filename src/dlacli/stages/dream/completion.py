"""The completion prior in dream's body backend (`dla dream --prior`, docs/dream.md "The
completion prior"): a network trained here (nn/completion.py, `dla train --method completion`)
corrects the hand-written fill (`texture.complete`) where the photo does not see the body.

1. Evidence (`photo_evidence`): the photo baked onto the displaced body at the network's UV
   resolution r (128) and completed by the rule there, exactly as at resolution R.
2. Inputs (`prior_inputs`): those maps plus the texels' fixed features (valid mask, body part,
   rest-pose point) as one [22, r, r] tensor.
3. Correction (`correct`): t = net(inputs), padded past its UV charts with the nearest valid
   texel's value, upsampled bilinearly to R, and applied at R as
   colour = corrected_colour(rule colour, t (1 - a)), a = min(weight / SEEN, 1) the photo's own
   confidence at R: texels the photo sees well keep its colour.

Texel arrays are flat over `dlacli.body.uv.valid_texels(r)` (row-major), as in stages/dream/texture.py.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.limits import DEFAULT_PRIOR as DEFAULT_PRIOR
from dlacli.types import Cameras

SHIPPED = Path(__file__).resolve().parents[2] / "assets" / "weights" / "completion"
PRIORS = ("none", "shipped")  # besides a checkpoint folder or hash


def grid(values: np.ndarray, resolution: int) -> np.ndarray:
    """Texel values [N, C] -> [C, R, R] float32 maps, 0 at texels no chart covers."""
    from dlacli.body.uv import valid_texels

    rows, cols, _ = valid_texels(resolution)
    out = np.zeros((values.shape[1], resolution, resolution), np.float32)
    out[:, rows, cols] = np.asarray(values, np.float32).T
    return out


@functools.lru_cache(maxsize=2)
def static_inputs(resolution: int) -> np.ndarray:
    """[15, R, R] the texels' fixed features: valid (1), body part one-hot (11, PARTS order), the
    rest-pose point in metres (3; anny's rest body spans about +-1 m)."""
    from dlacli.body.regions import PARTS
    from dlacli.stages.dream.texture import rest_texel_points, texel_samples

    _, _, part = texel_samples(resolution)
    onehot = np.zeros((part.size, len(PARTS)), np.float32)
    onehot[np.arange(part.size), part] = 1.0
    feats = np.concatenate([np.ones((part.size, 1), np.float32), onehot, rest_texel_points(resolution)], axis=1)
    return grid(feats, resolution)


def confidence(weight: np.ndarray) -> np.ndarray:
    """[N] the photo's confidence a = min(weight / SEEN, 1), as `texture.complete` uses it."""
    from dlacli.stages.dream.texture import SEEN

    return np.clip(np.asarray(weight, np.float32) / SEEN, 0.0, 1.0)


def prior_inputs(colour: np.ndarray, weight: np.ndarray, completed: np.ndarray, resolution: int) -> torch.Tensor:
    """The network's input [22, r, r] from the bake at r (colour [N, 3], weight [N]) and the
    rule's completion at r (completed [N, 3])."""
    a = confidence(weight)[:, None]
    texels = np.concatenate([completed, colour * a, a], axis=1)
    return torch.from_numpy(np.concatenate([grid(texels, resolution), static_inputs(resolution)]))


def photo_evidence(rgb, alpha, camera: Cameras, displaced: np.ndarray, resolution: int):
    """Step 1: (colour [N, 3], weight [N], completed [N, 3]) of the framed photo on the
    displaced body [V, 3] at UV resolution `resolution`."""
    from dlacli.stages.dream.texture import bake, complete

    colour, weight = bake(rgb, alpha, camera, displaced, resolution)
    return colour, weight, complete(colour, weight, resolution)


@functools.lru_cache(maxsize=2)
def _nearest_valid(resolution: int) -> tuple[np.ndarray, np.ndarray]:
    from scipy import ndimage

    from dlacli.body.uv import uv_raster

    _, (iy, ix) = ndimage.distance_transform_edt(~uv_raster(resolution).mask, return_indices=True)
    return iy, ix


def correct(net, inputs: torch.Tensor, completed: np.ndarray, weight: np.ndarray, resolution: int) -> np.ndarray:
    """Step 3: the rule's colours at R (completed [N, 3], the bake's weight [N]) corrected by the
    network's t for `inputs` [22, r, r] -> [N, 3] float32."""
    from dlacli.body.uv import valid_texels
    from dlacli.nn.completion import corrected_colour

    r = net.config.resolution
    with torch.no_grad():
        t = net(inputs[None].float())[0]  # [3, r, r]
        iy, ix = _nearest_valid(r)
        t = t[:, torch.from_numpy(iy), torch.from_numpy(ix)]  # padded past the charts
        if resolution != r:
            t = torch.nn.functional.interpolate(t[None], size=(resolution, resolution), mode="bilinear")[0]
        rows, cols, _ = valid_texels(resolution)
        t = t[:, torch.from_numpy(rows), torch.from_numpy(cols)].T  # [N, 3]
        unseen = torch.from_numpy(1.0 - confidence(weight))[:, None]
        out = corrected_colour(torch.from_numpy(np.asarray(completed, np.float32)), t * unseen)
    return out.numpy().astype(np.float32)


class CompletionPrior:
    """A completion network and the hash of its checkpoint: what the body backend's `prior` is
    (`texture.textured_body` calls `fill`). Called like the network."""

    def __init__(self, net, checkpoint_hash: str | None = None):
        self.net, self.checkpoint_hash = net, checkpoint_hash

    @property
    def config(self):
        return self.net.config

    def __call__(self, inputs: torch.Tensor) -> torch.Tensor:
        return self.net(inputs)

    def fill(self, rgb, alpha, camera: Cameras, displaced, completed, weight, resolution: int) -> np.ndarray:
        """Steps 1-3: the rule's colours at R (completed [N, 3], the bake's weight [N]) of the
        framed photo (rgb, alpha, camera) on the displaced body [V, 3], corrected -> [N, 3]."""
        r = self.config.resolution
        inputs = prior_inputs(*photo_evidence(rgb, alpha, camera, displaced, r), r)
        return correct(self.net, inputs, completed, weight, resolution)


def load_prior(spec: str | None) -> CompletionPrior | None:
    """--prior: "none" (or None) -> None; "shipped" -> the weights in the package; else a
    checkpoint folder or hash (`dla train --method completion`). The network in eval mode; a
    missing, corrupted or foreign checkpoint is a one-line DlaInputError."""
    from dlacli.avatar.checkpoint import load_checkpoint, resolve_checkpoint
    from dlacli.nn.completion import CompletionNet

    if spec is None or spec == "none":
        return None
    if spec == "shipped":
        if not SHIPPED.is_dir():
            raise DlaInputError("--prior", "this package ships no completion prior; use --prior none or a checkpoint")
        path = SHIPPED
    else:
        path = resolve_checkpoint(spec)
    loaded = load_checkpoint(path)
    if not isinstance(loaded.module, CompletionNet):
        raise DlaInputError(
            path,
            f"is a {type(loaded.module).__name__} checkpoint, not a completion prior (dla train --method completion)",
        )
    return CompletionPrior(loaded.module, loaded.hash)  # the hash: what the view folder records
