"""`dla synth --seeds`: many synthetic subjects in one dataset folder with a manifest
(formats/dataset.md), written by parallel processes and resumable; each subject is
`dlacli.data.synth.synth` with the dataset's settings."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dlacli.data.appearance import APPEARANCES
from dlacli.data.cameras import POSE_AZIMUTHS
from dlacli.data.synth import SUBJECT_LAYOUT, check_options, synth
from dlacli.errors import DlaInputError, excerpt, one_line

Progress = Callable[[str], None]

DATASET_FORMAT = "dla.dataset/1"
# a dataset's appearance: one for every subject, or "mixed" (each subject's drawn from its seed)
DATASET_APPEARANCES = (*APPEARANCES, "mixed")
MANIFEST = "manifest.json"
MOTION_SUFFIXES = (".bvh", ".amc", ".npz")


@dataclass(frozen=True)
class DatasetSettings:
    """What every subject of a dataset folder shares (formats/dataset.md); the seeds are not part of it."""

    res: int = 256
    novel_views: int = 8
    novel_poses: int = 8
    appearance: str = "lit"
    wardrobe: str = "full"
    motions: tuple[str, ...] = ()  # motion files for the target poses (the built-in motions are always used)

    def clips(self) -> list[str]:
        """The target-pose clips: the built-in motion names, then the motion files (absolute paths)."""
        from dlacli.body.builtin_motions import BUILTINS

        return list(BUILTINS) + [str(Path(m).resolve()) for m in self.motions]

    def record(self) -> dict:
        """The manifest's "settings" block (motion files by name and content hash, not by path)."""
        import hashlib

        import dlacli
        from dlacli.body.builtin_motions import BUILTINS

        files = [
            {"name": Path(m).name, "sha256": hashlib.sha256(Path(m).read_bytes()).hexdigest()} for m in self.motions
        ]
        return {
            "res": self.res,
            "input_views": 4,
            "novel_views": self.novel_views,
            "novel_poses": self.novel_poses,
            "pose_cameras": len(POSE_AZIMUTHS),
            "appearance": self.appearance,
            "wardrobe": self.wardrobe,
            "builtin_motions": list(BUILTINS),
            "motion_files": files,
            "input_rig": "random_yaw",
            "generator": "dla synth",
            "dla_version": dlacli.__version__,
        }


def motion_files(paths: Sequence[str | os.PathLike]) -> tuple[str, ...]:
    """Motion files from files and folders (a folder gives its .bvh, .amc and .npz files, sorted)."""
    out: list[str] = []
    for raw in paths:
        path = Path(raw)
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.suffix.lower() in MOTION_SUFFIXES and p.is_file())
            if not found:
                raise DlaInputError(path, f"holds no motion files ({', '.join(MOTION_SUFFIXES)})")
            out.extend(str(p) for p in found)
        elif path.is_file():
            if path.suffix.lower() not in MOTION_SUFFIXES:
                raise DlaInputError(path, f"is not a motion file ({', '.join(MOTION_SUFFIXES)})")
            out.append(str(path))
        else:
            raise DlaInputError(path, "no such motion file or folder")
    return tuple(out)


def subject_appearance(seed: int, appearance: str) -> str:
    """The appearance subject `seed` of a dataset with `appearance` is drawn in: the dataset's own,
    or for "mixed" lit or albedo with equal odds from a stream of the seed's own
    (`default_rng([seed, 6])`); the subject is then the one a dataset of that appearance holds."""
    if appearance != "mixed":
        return appearance
    return APPEARANCES[int(np.random.default_rng([int(seed), 6]).integers(len(APPEARANCES)))]


def subject_name(seed: int) -> str:
    return f"subject_{int(seed)}"


def subject_complete(folder: Path, settings: DatasetSettings) -> bool:
    """Whether `folder` holds every file a subject of `settings` has (synth writes it atomically,
    so a folder that exists is whole unless someone changed it)."""
    parts = {"": 4, "novel_views": settings.novel_views, "novel_poses": settings.novel_poses * len(POSE_AZIMUTHS)}
    for sub, n in parts.items():
        where = folder / sub
        if n == 0:
            if sub and where.exists():
                return False
            continue
        if not ((where / "transforms.json").is_file() and (where / "body.json").is_file()):
            return False
        if len(list((where / "images").glob("view_*.png"))) != n:
            return False
    return not settings.novel_poses or (folder / "novel_poses" / "motion.npz").is_file()


def synth_record(folder: Path) -> dict:
    """The `"dla": {"synth": {...}}` object of a subject folder's transforms.json (formats/dataset.md;
    {} when absent), read through the view-folder reader, so a file that is no valid transforms.json
    is a DlaInputError naming it."""
    from dlacli.io.views import TRANSFORMS, read_transforms

    info = read_transforms(folder)["dla"].get("synth", {})
    if not isinstance(info, dict):
        raise DlaInputError(folder / TRANSFORMS, f"'dla.synth' must be an object, found {type(info).__name__}")
    return info


def _subject_entry(folder: Path, seed: int, seconds: float | None) -> dict:
    info = synth_record(folder)
    size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    return {
        "seed": int(seed),
        "path": folder.name,
        "outfit": info.get("outfit"),
        "suit_pattern": info.get("suit_pattern"),
        "appearance": info.get("appearance", "albedo"),
        "wardrobe": info.get("wardrobe", "default"),
        "start_yaw": info.get("start_yaw"),
        "seconds": None if seconds is None else round(float(seconds), 3),
        "bytes": int(size),
    }


def _write_manifest(path: Path, settings: dict, entries: dict[int, dict]) -> dict:
    from dlacli.io.atomic import atomic_path
    from dlacli.io.validate import dump_json

    subjects = [entries[s] for s in sorted(entries)]
    secs = [e["seconds"] for e in subjects if e["seconds"] is not None]
    manifest = {
        "format": DATASET_FORMAT,
        "settings": settings,
        "seconds_per_subject": round(float(np.mean(secs)), 3) if secs else None,
        "bytes_per_subject": int(np.mean([e["bytes"] for e in subjects])) if subjects else None,
        "subjects": subjects,
    }
    with atomic_path(path) as tmp:
        tmp.write_text(dump_json(manifest) + "\n", encoding="utf-8")
    return manifest


def read_manifest(path: str | os.PathLike) -> dict:
    """A dataset's manifest.json, checked (formats/dataset.md): format, a settings object and a list
    of subjects, each an object with a seed (an integer >= 0), a path (one folder name inside the
    dataset) and, where present, seconds (null or a number >= 0) and bytes (an integer >= 0); no
    seed or path twice."""
    from dlacli.io.validate import check_format, load_json

    path = Path(path)
    data = load_json(path)
    if not isinstance(data, dict):
        raise DlaInputError(path, "is not a JSON object")
    check_format(data.get("format"), DATASET_FORMAT, path)
    if not isinstance(data.get("settings"), dict):
        raise DlaInputError(path, "missing the 'settings' object")
    subjects = data.get("subjects")
    if not isinstance(subjects, list):
        raise DlaInputError(path, "'subjects' must be a list of objects with an integer 'seed' and a 'path'")
    seen: set = set()
    for i, entry in enumerate(subjects):
        _check_subject(entry, path, f"subjects[{i}]")
        for key in ("seed", "path"):
            if (key, entry[key]) in seen:
                raise DlaInputError(path, f"subjects[{i}] repeats the {key} {excerpt(entry[key])}")
            seen.add((key, entry[key]))
    return data


def _whole(value, low: int = 0) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


def _check_subject(entry, path: Path, at: str) -> None:
    """One `subjects[]` entry of a manifest (read_manifest)."""
    if not isinstance(entry, dict):
        raise DlaInputError(
            path, f"{at} must be an object with an integer 'seed' and a 'path', found {type(entry).__name__}"
        )
    seed, name = entry.get("seed"), entry.get("path")
    if not _whole(seed):
        raise DlaInputError(path, f"{at}.seed must be an integer >= 0, found {excerpt(seed)}")
    if not (isinstance(name, str) and name.isprintable() and 0 < len(name.encode()) <= 255 and name not in (".", "..")):
        raise DlaInputError(path, f"{at}.path must be a folder name, found {excerpt(name)}")
    if "/" in name or "\\" in name:
        raise DlaInputError(path, f"{at}.path {excerpt(name)} is not one folder name inside the dataset")
    seconds = entry.get("seconds")
    if seconds is not None and not (
        isinstance(seconds, (int, float)) and not isinstance(seconds, bool) and 0 <= seconds < float("inf")
    ):
        raise DlaInputError(path, f"{at}.seconds must be null or a number >= 0, found {excerpt(seconds)}")
    if "bytes" in entry and not _whole(entry["bytes"]):
        raise DlaInputError(path, f"{at}.bytes must be an integer >= 0, found {excerpt(entry['bytes'])}")


def _differences(old: dict, new: dict) -> str:
    """The first 3 settings that differ, each quoted as an excerpt (a manifest may hold anything)."""

    def show(key: str, value) -> str:
        if key == "motion_files" and isinstance(value, list):
            value = [f"{m.get('name')} ({str(m.get('sha256'))[:8]})" if isinstance(m, dict) else m for m in value]
        return excerpt(value)

    keys = [k for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
    return "; ".join(f"{one_line(k, 40)} {show(k, old.get(k))} there, {show(k, new.get(k))} now" for k in keys[:3])


def single_threaded() -> tuple[int, int]:
    """Pin torch and numba to one thread (a dataset worker; results then do not depend on --jobs)."""
    import numba

    before = (torch.get_num_threads(), numba.get_num_threads())
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    return before


def _make_subject(task: tuple[int, str, dict]) -> tuple[int, float, tuple[str | None, str] | None]:
    """Worker: write one subject; -> (seed, seconds, (where, problem) of a DlaInputError or None:
    DlaInputError does not survive pickling between processes)."""
    seed, folder, kw = task
    start = time.perf_counter()
    try:
        synth(seed, folder, random_yaw=True, **kw)
    except DlaInputError as err:
        return seed, time.perf_counter() - start, (err.where, err.problem)
    return seed, time.perf_counter() - start, None


def synth_dataset(
    seeds: Sequence[int],
    out: str | os.PathLike,
    settings: DatasetSettings,
    *,
    jobs: int = 1,
    progress: Progress | None = None,
) -> dict:
    """Write subjects `seeds` into the dataset folder `out` (out/subject_<seed>/, out/manifest.json)
    with `jobs` processes; subjects already complete are skipped, so a rerun resumes. A manifest
    with other settings is refused. Returns the manifest."""
    from dlacli.io.atomic import check_outputs

    seeds = [int(s) for s in seeds]
    if not seeds or any(s < 0 for s in seeds) or len(set(seeds)) != len(seeds):
        raise DlaInputError("--seeds", "must be distinct non-negative integers")
    if not isinstance(jobs, int) or jobs < 1:
        raise DlaInputError("--jobs", f"must be an integer >= 1, got {jobs!r}")
    if settings.appearance not in DATASET_APPEARANCES:
        raise DlaInputError(
            "--appearance", f"must be one of {', '.join(DATASET_APPEARANCES)}, got {settings.appearance!r}"
        )
    concrete = subject_appearance(0, settings.appearance)
    check_options(settings.res, settings.novel_views, settings.novel_poses, concrete, settings.wardrobe)
    say = progress or (lambda msg: None)
    out = Path(out)
    layout = [MANIFEST, "subject_*", *(f"subject_*/{p}" for p in SUBJECT_LAYOUT)]
    check_outputs(folders=[(out, layout)])
    record = settings.record()
    path = out / MANIFEST
    entries: dict[int, dict] = {}
    if path.exists():
        old = read_manifest(path)
        if old["settings"] != record:
            raise DlaInputError(
                path,
                f"was written with other settings ({_differences(old['settings'], record)}); "
                "use the same options or another folder",
            )
        # an entry without its seconds and bytes is made again below, as for a subject the manifest lacks
        entries = {
            e["seed"]: e for e in old["subjects"] if (out / e["path"]).is_dir() and {"seconds", "bytes"} <= e.keys()
        }
    elif out.exists() and any(out.iterdir()):
        raise DlaInputError(out, f"is not empty and holds no {MANIFEST}: not a dla dataset folder")
    out.mkdir(parents=True, exist_ok=True)
    todo = []
    for seed in seeds:
        folder = out / subject_name(seed)
        if subject_complete(folder, settings):
            if seed not in entries:  # made by a run stopped before its manifest update
                entries[seed] = _subject_entry(folder, seed, None)
        else:
            entries.pop(seed, None)
            todo.append(seed)
    _write_manifest(path, record, entries)
    say(f"{len(todo)} subjects to write, {len(seeds) - len(todo)} already complete")
    kw = dict(
        res=settings.res,
        novel_views=settings.novel_views,
        novel_poses=settings.novel_poses,
        wardrobe=settings.wardrobe,
        motions=settings.clips(),
    )
    tasks = [
        (seed, str(out / subject_name(seed)), {**kw, "appearance": subject_appearance(seed, settings.appearance)})
        for seed in todo
    ]
    manifest = None

    def finished(n: int, seed: int, seconds: float, error: tuple[str | None, str] | None) -> None:
        nonlocal manifest
        if error is not None:
            raise DlaInputError(*error)
        entries[seed] = _subject_entry(out / subject_name(seed), seed, seconds)
        manifest = _write_manifest(path, record, entries)
        say(f"{subject_name(seed)}: {seconds:.1f} s, {entries[seed]['bytes'] / 1e6:.2f} MB ({n}/{len(todo)})")

    if jobs == 1 or len(tasks) <= 1:
        before = single_threaded()
        try:
            for n, task in enumerate(tasks, start=1):
                finished(n, *_make_subject(task))
        finally:
            import numba

            torch.set_num_threads(before[0])
            numba.set_num_threads(before[1])
    else:
        import concurrent.futures as cf
        import multiprocessing

        # an executor, not multiprocessing.Pool: a worker that dies (killed, out of memory) breaks
        # the pool with an error instead of being replaced while its subject waits forever
        ctx = multiprocessing.get_context("spawn")
        with cf.ProcessPoolExecutor(min(jobs, len(tasks)), mp_context=ctx, initializer=single_threaded) as pool:
            futures = [pool.submit(_make_subject, task) for task in tasks]
            try:
                for n, fut in enumerate(cf.as_completed(futures), start=1):
                    finished(n, *fut.result())
            except cf.process.BrokenProcessPool:
                raise RuntimeError("dla synth: a worker process died (out of memory?); rerun to resume") from None
            finally:  # on any error, do not wait for the subjects not started yet
                for fut in futures:
                    fut.cancel()
    return manifest or read_manifest(path)
