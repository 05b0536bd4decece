"""The pose lifter: a person's 3D keypoints from their COCO-17 keypoints in one image.

A small MLP in the manner of Martinez et al.'s "simple yet effective baseline" for 3D human pose:
the 17 keypoints, as camera rays, centred on the hips and scaled by the torso's length in the
image, go in (with which of them were seen, and where the hips are in the image); the 17 points
in camera axes (x right, y down, z away from the camera), centred on the hips and scaled by the
torso's 3D length, come out. `dla motion from-video` averages its limb directions with those of
MediaPipe's 3D landmarks for the fit's limb prior (docs/motion.md). It is trained here, on anny
poses retargeted from CMU motion capture and random flexions, seen by random cameras
(`dlacli.train.lifter`, docs/train.md); the shipped weights are
`assets/weights/lifter/lifter.safetensors` (float16, the config in its metadata).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from dlacli.body.keypoints import COCO_MIRROR, HIPS, MIN_CONF, NUM_KEYPOINTS, SHOULDERS

NUM_INPUTS = 3 * NUM_KEYPOINTS + 3
WEIGHTS = Path(__file__).resolve().parents[1] / "assets" / "weights" / "lifter" / "lifter.safetensors"


@dataclass(frozen=True)
class LifterConfig:
    width: int = 512
    blocks: int = 2
    dropout: float = 0.1


class _Block(nn.Module):
    def __init__(self, width: int, dropout: float) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(width, width),
            nn.LayerNorm(width),
            nn.ReLU(),
            nn.Dropout(dropout),
            nn.Linear(width, width),
            nn.LayerNorm(width),
            nn.ReLU(),
            nn.Dropout(dropout),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.net(x)


class PoseLifter(nn.Module):
    """[B, NUM_INPUTS] (`lifter_inputs`) -> [B, 17, 3] hip-centred points, torso lengths."""

    def __init__(self, config: LifterConfig | None = None) -> None:
        super().__init__()
        self.config = config or LifterConfig()
        c = self.config
        self.inp = nn.Linear(NUM_INPUTS, c.width)
        self.blocks = nn.Sequential(*[_Block(c.width, c.dropout) for _ in range(c.blocks)])
        self.out = nn.Linear(c.width, 3 * NUM_KEYPOINTS)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.blocks(torch.relu(self.inp(x)))).reshape(-1, NUM_KEYPOINTS, 3)


def lifter_inputs(rays: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
    """rays [B, 17, 2] (image-plane coordinates (u - cx) / f, (v - cy) / f), seen [B, 17] bool ->
    [B, NUM_INPUTS]: per keypoint (ray - hip centre) / torso length and the seen flag (0, 0, 0
    where unseen), then the hip centre and the torso length. Each row needs a seen hip and a seen
    shoulder (a frame without them has no person, stages/motion/video.py)."""
    w = seen.float()

    def centre(idx: tuple[int, int]) -> torch.Tensor:
        ws = w[:, list(idx), None]
        return (rays[:, list(idx)] * ws).sum(1) / ws.sum(1).clamp(min=1.0)

    hip = centre(HIPS)  # [B, 2]
    torso = (centre(SHOULDERS) - hip).norm(dim=-1).clamp(min=1e-4)  # [B]
    rel = (rays - hip[:, None]) / torso[:, None, None] * w[..., None]
    return torch.cat([torch.cat([rel, w[..., None]], -1).reshape(-1, 3 * NUM_KEYPOINTS), hip, torso[:, None]], 1)


def lifter_targets(points: torch.Tensor) -> torch.Tensor:
    """3D keypoints [B, 17, 3] in camera axes -> hip-centred, in torso lengths (the network's output)."""
    hip = points[:, list(HIPS)].mean(1, keepdim=True)
    torso = (points[:, list(SHOULDERS)].mean(1, keepdim=True) - hip).norm(dim=-1, keepdim=True)
    return (points - hip) / torso.clamp(min=1e-6)


def save_lifter(model: PoseLifter, path: str | Path, meta: dict | None = None) -> None:
    """Weights in float16 as safetensors, the config and `meta` as JSON in its metadata."""
    import json

    from safetensors.torch import save_file

    state = {k: v.detach().half().contiguous() for k, v in model.state_dict().items()}
    save_file(state, str(path), metadata={"config": json.dumps(asdict(model.config)), "meta": json.dumps(meta or {})})


MAX_BYTES = 64 << 20  # a lifter file larger than this is refused (the shipped one is ~2 MB)


def load_lifter(path: str | Path | None = None) -> PoseLifter:
    """A saved lifter (the shipped `WEIGHTS` by default) in eval mode, float32 on the CPU.
    DlaInputError naming the file when it is not one (`save_lifter`'s layout)."""
    import json

    from safetensors import safe_open

    from dlacli.errors import DlaInputError

    path = Path(WEIGHTS if path is None else path)
    if not path.is_file():
        raise DlaInputError(path, "no such lifter weights file")
    if path.stat().st_size > MAX_BYTES:
        raise DlaInputError(path, f"is {path.stat().st_size >> 20} MB; a lifter's weights are a few MB")
    try:
        with safe_open(str(path), framework="pt") as f:
            config = LifterConfig(**json.loads(f.metadata()["config"]))
            state = {k: f.get_tensor(k).float() for k in f.keys()}  # noqa: SIM118 - safe_open has no iterator
        model = PoseLifter(config)
        model.load_state_dict(state)
    except Exception as err:  # noqa: BLE001 - any unreadable or foreign file is the same input error
        raise DlaInputError(
            path, f"not pose-lifter weights (`dla train --method lifter`): {type(err).__name__}"
        ) from None
    return model.eval()


@torch.no_grad()
def lift_keypoints(keypoints: np.ndarray, K: np.ndarray, model: PoseLifter | None = None) -> np.ndarray:
    """keypoints [N, 17, 3] (pixels, confidence) seen through intrinsics K -> [N, 17, 4]: 3D points
    in camera axes (hip-centred, torso lengths) and each keypoint's confidence (0 where unseen),
    the layout of MediaPipe's world landmarks that the fit's limb prior reads. The points are the
    mean of the lift of the keypoints and the mirrored lift of their mirror image."""
    kp = np.asarray(keypoints, np.float32)
    model = model or load_lifter()
    seen = torch.from_numpy(kp[..., 2] >= MIN_CONF)
    rays = torch.from_numpy(np.stack([(kp[..., 0] - K[0, 2]) / K[0, 0], (kp[..., 1] - K[1, 2]) / K[1, 1]], -1))
    flip = torch.tensor([-1.0, 1.0])
    mirrored = (rays * flip)[:, list(COCO_MIRROR)]
    both = model(lifter_inputs(torch.cat([rays, mirrored]).float(), torch.cat([seen, seen[:, list(COCO_MIRROR)]])))
    n = kp.shape[0]
    back = both[n:, list(COCO_MIRROR)] * torch.tensor([-1.0, 1.0, 1.0])
    pts = (0.5 * (both[:n] + back)).numpy()
    conf = np.where(seen.numpy(), kp[..., 2], 0.0)
    return np.concatenate([pts, conf[..., None]], -1).astype(np.float32)
