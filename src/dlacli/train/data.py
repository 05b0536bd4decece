"""Training examples from synthetic subjects (`dla synth --seeds`, formats/dataset.md).

`TrainingData(root, input_size, target_size, targets)` reads a dataset folder (its manifest.json)
or one subject folder. An `Item` is one subject: its 4 input views at input_size, and `targets`
target views drawn with a caller's numpy Generator from the subject's novel views, novel poses
and (include_inputs) input views, each with its camera and the posed body that the image shows.

Images: straight RGBA PNGs are premultiplied (rgb * alpha: a black background) and area-averaged
to the requested size (`torch.nn.functional.interpolate(mode="area")`: exact box filtering for
integer factors, adaptive-average windows otherwise); cameras are rescaled with them (fx, fy,
cx, cy times size / width). Sizes larger than a folder's images are refused.

Cache (`cache=True`): per subject, the resized images as uint8 and the body vertices (anny's
13,718 vertices per pose, float32). Memory per subject: 4 S^2 4 + N H^2 4 bytes of images (N:
the pool of targets, 8 + 24 + 4 = 36 for the default dataset) + (2 + M) 13,718 x 12 bytes of
vertices (the input pose, M novel poses, the rest pose): at S = H = 256 with 8 novel views and
8 poses x 3 cameras, 10.5 MB + 1.6 MB = 12.1 MB; at S = 256, H = 128, 3.4 MB + 1.6 MB.
`max_cached` bounds how many subjects stay cached (least recently used first out).
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from dlacli.errors import DlaInputError, excerpt
from dlacli.types import Cameras

NUM_INPUTS = 4


@dataclass
class Item:
    """One training example, CPU float32 tensors (images with a black background)."""

    subject: str  # folder name
    input_rgb: torch.Tensor  # [4, 3, S, S] in [0, 1], rgb * alpha
    input_mask: torch.Tensor  # [4, 1, S, S]
    input_cameras: Cameras  # the 4 input cameras at S x S
    input_vertices: torch.Tensor  # [V, 3] anny vertices in the input pose (body.json)
    rest_vertices: torch.Tensor  # [V, 3] the subject's zero-pose vertices
    target_rgb: torch.Tensor  # [T, 3, H, H] in [0, 1], rgb * alpha
    target_mask: torch.Tensor  # [T, 1, H, H]
    target_cameras: Cameras  # T cameras at H x H
    target_vertices: torch.Tensor  # [T, V, 3] the posed body each target shows
    target_kind: list[str]  # [T] "view" (same pose as the inputs) or "pose"


@dataclass
class _Subject:
    """A subject's decoded, resized data (what the cache holds)."""

    inputs: np.ndarray  # [4, S, S, 4] uint8 premultiplied rgb + alpha
    input_cameras: Cameras
    pool: np.ndarray  # [N, H, H, 4] uint8 targets: novel views, novel-pose frames, then inputs
    pool_cameras: Cameras  # [N] at H
    pool_pose: np.ndarray  # [N] int64 index into vertices: 0 the input pose, 1 + t motion frame t
    pool_kind: list[str]  # [N]
    vertices: torch.Tensor  # [1 + M, V, 3] float32
    rest: torch.Tensor  # [V, 3] float32

    @property
    def nbytes(self) -> int:
        return int(self.inputs.nbytes + self.pool.nbytes + self.vertices.numel() * 4 + self.rest.numel() * 4)


def discover(root: Path) -> list[tuple[int | None, str, Path]]:
    """(seed or None, folder name, folder) of every subject under `root`, in manifest order."""
    from dlacli.data.dataset import MANIFEST, read_manifest

    if (root / MANIFEST).is_file():
        manifest = read_manifest(root / MANIFEST)
        return [(int(e["seed"]), Path(e["path"]).name, root / e["path"]) for e in manifest["subjects"]]
    if (root / "transforms.json").is_file():
        from dlacli.data.dataset import synth_record

        seed = synth_record(root).get("seed")
        return [(seed if isinstance(seed, int) and not isinstance(seed, bool) else None, root.name, root)]
    raise DlaInputError(
        root / MANIFEST,
        "missing: the root is neither a dataset folder (manifest.json) nor a subject folder (transforms.json)",
    )


def image_size(root: str | Path) -> int:
    """The long side in pixels of the views of the first subject under `root` (a dataset or
    subject folder): the size its targets hold their detail at."""
    from dlacli.io.views import read_transforms

    _, _, folder = discover(Path(root))[0]
    t = read_transforms(folder)
    return int(max(t["width"], t["height"]))


def split_subjects(root: str | Path, validation: int) -> tuple[list[str], list[str]]:
    """(train, validation) subject names: the `validation` lowest seeds validate (so the split
    stays when a dataset grows by higher seeds), the rest train; both in seed order."""
    found = discover(Path(root))
    if not isinstance(validation, int) or validation < 0 or validation >= len(found):
        raise DlaInputError(
            "validation", f"must be an integer in [0, {len(found) - 1}] for {len(found)} subjects, got {validation!r}"
        )
    ordered = [name for _, name, _ in sorted(found, key=lambda s: (s[0] is None, s[0] or 0, s[1]))]
    return ordered[validation:], ordered[:validation]


def _to_size(rgb: np.ndarray, alpha: np.ndarray, size: int, where: Path) -> np.ndarray:
    """rgb [N, h, w, 3], alpha [N, h, w] float in [0, 1] (straight) -> [N, size, size, 4] uint8
    premultiplied rgb + alpha, area-averaged."""
    if size > rgb.shape[1] or size > rgb.shape[2]:
        raise DlaInputError(where, f"images are {rgb.shape[2]}x{rgb.shape[1]}, smaller than the requested {size} px")
    x = torch.from_numpy(np.concatenate([rgb * alpha[..., None], alpha[..., None]], axis=-1)).permute(0, 3, 1, 2)
    if x.shape[-2:] != (size, size):
        x = F.interpolate(x, size=(size, size), mode="area")
    return (x.permute(0, 2, 3, 1) * 255.0).round().clamp(0, 255).to(torch.uint8).numpy()


def _cat_cameras(parts: list[Cameras], size: int) -> Cameras:
    return Cameras(torch.cat([c.viewmats for c in parts]), torch.cat([c.Ks for c in parts]), size, size)


def _select(cameras: Cameras, idx: np.ndarray) -> Cameras:
    i = torch.from_numpy(np.asarray(idx, np.int64))
    return Cameras(cameras.viewmats[i].clone(), cameras.Ks[i].clone(), cameras.width, cameras.height)


def _tensors(u8: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """[N, S, S, 4] uint8 -> (rgb [N, 3, S, S], mask [N, 1, S, S]) float32 in [0, 1]."""
    x = torch.from_numpy(u8).permute(0, 3, 1, 2).float() / 255.0
    return x[:, :3].contiguous(), x[:, 3:].contiguous()


class TrainingData:
    """The subjects of a dataset folder (manifest.json) or one subject folder, as `Item`s."""

    def __init__(
        self,
        root: str | Path,
        input_size: int,
        target_size: int,
        targets: int,
        subjects: list[str] | None = None,
        include_inputs: bool = True,
        cache: bool = True,
        max_cached: int | None = None,
    ) -> None:
        for name, value in (("input_size", input_size), ("target_size", target_size), ("targets", targets)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise DlaInputError(name, f"must be an integer >= 1, got {value!r}")
        self.root = Path(root)
        self.input_size, self.target_size, self.targets = input_size, target_size, targets
        self.include_inputs, self.cache, self.max_cached = include_inputs, cache, max_cached
        found = {name: folder for _, name, folder in discover(self.root)}
        if subjects is None:
            subjects = list(found)
        unknown = [s for s in subjects if s not in found]
        if unknown:
            raise DlaInputError(self.root, f"has no subject {excerpt(unknown[0])}")
        if not subjects:
            raise DlaInputError(self.root, "holds no subjects")
        self.subjects = list(subjects)
        self.folders = [found[s] for s in self.subjects]
        for folder in self.folders:
            if not folder.is_dir():
                raise DlaInputError(folder, "missing: a subject folder the manifest lists")
        self._cache: collections.OrderedDict[int, _Subject] = collections.OrderedDict()

    def __len__(self) -> int:
        return len(self.subjects)

    def _load(self, index: int) -> _Subject:
        from dlacli.body.model import get_body_model
        from dlacli.io.motion import read_motion
        from dlacli.io.views import read_views

        folder = self.folders[index]
        s, h = self.input_size, self.target_size
        main = read_views(folder)
        if len(main) != NUM_INPUTS:
            raise DlaInputError(folder / "transforms.json", f"has {len(main)} views, a subject has {NUM_INPUTS} inputs")
        model = get_body_model()
        verts = [model.forward_body(main.body).vertices[0]]  # the input pose
        images, cams, pose, kind = [], [], [], []
        if (folder / "novel_views").is_dir():
            nv = read_views(folder / "novel_views", require_body=False)
            images.append(_to_size(nv.images, nv.masks, h, folder / "novel_views"))
            cams.append(nv.cameras.resized(h, h))
            pose += [0] * len(nv)
            kind += ["view"] * len(nv)
        if (folder / "novel_poses").is_dir():
            npv = read_views(folder / "novel_poses", require_body=False)
            motion = read_motion(folder / "novel_poses" / "motion.npz")
            times = np.asarray([-1 if t is None else t for t in npv.times])
            if times.min() < 0 or times.max() >= motion.num_frames:
                raise DlaInputError(
                    folder / "novel_poses" / "transforms.json",
                    f"frame times must index the {motion.num_frames} poses of motion.npz",
                )
            verts.extend(model.forward_motion(main.body.phenotype, motion).vertices)
            images.append(_to_size(npv.images, npv.masks, h, folder / "novel_poses"))
            cams.append(npv.cameras.resized(h, h))
            pose += (1 + times).tolist()
            kind += ["pose"] * len(npv)
        inputs = _to_size(main.images, main.masks, s, folder)
        if self.include_inputs:
            images.append(inputs if s == h else _to_size(main.images, main.masks, h, folder))
            cams.append(main.cameras.resized(h, h))
            pose += [0] * len(main)
            kind += ["view"] * len(main)
        if not images:
            raise DlaInputError(folder, "has no target views (no novel_views/, no novel_poses/, inputs excluded)")
        rest = torch.from_numpy(np.asarray(model.rest_vertices(main.body.phenotype), np.float32))
        return _Subject(
            inputs,
            main.cameras.resized(s, s),
            np.concatenate(images),
            _cat_cameras(cams, h),
            np.asarray(pose, np.int64),
            kind,
            torch.stack(verts).float().contiguous(),
            rest,
        )

    def _subject(self, index: int) -> _Subject:
        if not 0 <= index < len(self):
            raise IndexError(f"subject index {index} out of range for {len(self)} subjects")
        if not self.cache:
            return self._load(index)
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        subject = self._load(index)
        self._cache[index] = subject
        while self.max_cached is not None and len(self._cache) > max(self.max_cached, 0):
            self._cache.popitem(last=False)
        return subject

    def item(self, index: int, rng: np.random.Generator) -> Item:
        """Subject `index` with `targets` targets drawn by `rng` (without replacement when the
        pool is large enough); the same index and rng state give the same Item."""
        n = self._subject(index).pool.shape[0]
        return self.item_at(index, rng.choice(n, size=self.targets, replace=n < self.targets))

    def kinds(self, index: int) -> list[str]:
        """The kind ("view" or "pose") of each target in subject `index`'s pool, in pool order."""
        return list(self._subject(index).pool_kind)

    def item_at(self, index: int, pick) -> Item:
        """Subject `index` with the targets at pool positions `pick` (`kinds` lists the pool)."""
        sub = self._subject(index)
        pick = np.asarray(pick, np.int64)
        in_rgb, in_mask = _tensors(sub.inputs)
        t_rgb, t_mask = _tensors(sub.pool[pick])
        return Item(
            subject=self.subjects[index],
            input_rgb=in_rgb,
            input_mask=in_mask,
            input_cameras=_select(sub.input_cameras, np.arange(NUM_INPUTS)),
            input_vertices=sub.vertices[0].clone(),
            rest_vertices=sub.rest.clone(),
            target_rgb=t_rgb,
            target_mask=t_mask,
            target_cameras=_select(sub.pool_cameras, pick),
            target_vertices=sub.vertices[torch.from_numpy(sub.pool_pose[pick])].clone(),
            target_kind=[sub.pool_kind[i] for i in pick],
        )

    def batch(self, indices: list[int], rng: np.random.Generator) -> list[Item]:
        """`item` for each index in turn, drawing from the one `rng`."""
        return [self.item(int(i), rng) for i in indices]

    def cached_bytes(self) -> int:
        """Memory the cache holds now."""
        return sum(s.nbytes for s in self._cache.values())
