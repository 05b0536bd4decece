"""A seeded mutation fuzzer over every reader dla has (issue 20).

Seeds are the golden files of formats/examples and the third-party files of tests/data (cut short
where they are long), plus files the writers make here (.spz, .splat, AMASS, a checkpoint, a
train.json) and a hand-written dataset folder (formats/dataset.md: a manifest and one subject).
Each run copies one seed target into a fresh folder, mutates one of its files (bit flips, cut,
inserted or repeated bytes; in JSON, a value swapped for a huge number, deep nesting, NaN, a long
string or a wrong type; in .npz, an array swapped for another dtype, shape or extreme values; in
text, numbers swapped for extreme ones and lines dropped or repeated) and calls every
reader of that format in-process. Each reader must return or raise DlaInputError with one short
line that names a file of the run, within a few seconds, leaving the files as they were and adding
none. A handful of mutated files also go through `dla info` to check exit code 2 and one stderr
line. The seed is fixed, so a failure names the run that reproduces it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import shutil
import signal
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from dlacli.errors import DlaInputError

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "formats" / "examples"
DATA = ROOT / "tests" / "data"
SEED = 20
RUNS = 300  # mutations per target (21 targets, 2-4 readers each: ~12,000 reader calls)
SECONDS_PER_RUN = 20.0  # a reader still busy after this is a hang
MAX_MESSAGE = 300  # characters of a message beyond the file name it starts with

# raw JSON text swapped in for one value: numbers beyond float64 and Python's digit limit,
# constants JSON lacks, deep nesting, a long string, a lone surrogate, wrong types
JSON_VALUES = [
    *'NaN -Infinity 1e308 -1e-320 0 -1 2147483648 18446744073709551617 true null "" [] {} [1,2,3] 0.5'.split(),
    *['"\\ud800"', '"../../../etc/passwd"', "1" + "0" * 309, "9" * 5000, json.dumps("x" * 100_000)],
    *["[" * 1500 + "]" * 1500, '{"a":' * 80 + "1" + "}" * 80, json.dumps([[1e30] * 3] * 4)],
]
TEXT_NUMBERS = [
    "",
    *"1e20 -1e20 1e309 nan -inf 1e-400 0 -0 99999999999999999999 7e5 0x10 1_000 1e --1".split(),
    "\u0661",
]
TEXT_LINES = ["{", "}", "JOINT x", "End Site", "MOTION", "Frames: 999999999", "Frame Time: 0", ":radians", "ROOT"]
TEXT_LINES += ["CHANNELS 7 Xrotation", "OFFSET 1e300 0 0", "begin", "end", ":hierarchy", "root root"]


@dataclasses.dataclass
class Target:
    """A seed: its files (relative path -> bytes), which of them the fuzzer mutates and how, and
    the readers of the format, each called with the run's folder."""

    name: str
    files: dict[str, bytes]
    mutable: dict[str, str]  # relative path -> "bytes" | "json" | "text" | "npz"
    readers: list[Callable[[Path], object]]
    info: str | None = None  # the path `dla info` takes, for the CLI runs
    max_message: int = MAX_MESSAGE
    agree: tuple[tuple[int, int], ...] = ((0, -1),)  # readers that must refuse the same files: a
    # command's reader (first) and `dla info`'s (last) share their checks


# ------------------------------------------------------------------------------------ mutations


def mutate_bytes(rng: np.random.Generator, data: bytes) -> bytes:
    b = bytearray(data)
    if not b:
        return bytes(rng.integers(0, 256, 16, dtype=np.uint8))
    kind = rng.integers(6)
    if kind == 0:  # flip bits
        for _ in range(rng.integers(1, 9)):
            b[rng.integers(len(b))] ^= 1 << int(rng.integers(8))
    elif kind == 1:  # interesting bytes
        for _ in range(rng.integers(1, 5)):
            b[rng.integers(len(b))] = int(rng.choice([0x00, 0xFF, 0x7F, 0x80, 0x46, 0x30]))
    elif kind == 2:  # cut
        b = b[: rng.integers(len(b))]
    elif kind == 3:  # insert random bytes
        at = rng.integers(len(b) + 1)
        b[at:at] = rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
    elif kind == 4:  # repeat a chunk
        at, n = rng.integers(len(b)), rng.integers(1, 64)
        b[at:at] = bytes(b[at : at + n]) * int(rng.integers(2, 50))
    else:  # delete a chunk
        at = rng.integers(len(b))
        del b[at : at + int(rng.integers(1, 64))]
    return bytes(b)


def _nodes(value, path=()):
    yield path
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _nodes(v, (*path, k))
    elif isinstance(value, list):
        for i, v in enumerate(value[:64]):
            yield from _nodes(v, (*path, i))


def mutate_json(rng: np.random.Generator, data: bytes) -> bytes:
    try:
        doc = json.loads(data)
    except ValueError:
        return mutate_bytes(rng, data)
    if rng.random() < 0.15:
        return mutate_bytes(rng, data)
    nodes = list(_nodes(doc))
    path = nodes[rng.integers(len(nodes))]
    marker = "\x00FUZZ\x00"
    kind = rng.integers(4)
    if not path or kind == 0:  # swap a value for raw text
        raw = JSON_VALUES[rng.integers(len(JSON_VALUES))]
        if not path:
            return raw.encode()
        _set(doc, path, marker)
        return json.dumps(doc).replace(json.dumps(marker), raw).encode()
    parent = _get(doc, path[:-1])
    if kind == 1:  # drop it
        del parent[path[-1]]
    elif kind == 2 and isinstance(parent, dict):  # an unknown key
        parent["zz" * int(rng.integers(1, 4))] = 1
    elif kind == 2:  # repeat a list item
        parent.extend([parent[path[-1]]] * int(rng.integers(1, 200)))
    else:  # a value of another type
        _set(doc, path, [None, "text", 3, 2.5, [], {}, False][rng.integers(7)])
    return json.dumps(doc).encode()


def _get(doc, path):
    for key in path:
        doc = doc[key]
    return doc


def _set(doc, path, value):
    _get(doc, path[:-1])[path[-1]] = value


def mutate_text(rng: np.random.Generator, data: bytes) -> bytes:
    if rng.random() < 0.2:
        return mutate_bytes(rng, data)
    lines = data.decode("utf-8", "replace").split("\n")
    kind = rng.integers(4)
    at = rng.integers(len(lines))
    if kind == 0:  # numbers swapped for extreme ones
        for _ in range(rng.integers(1, 4)):
            i = rng.integers(len(lines))
            words = lines[i].split()
            nums = [j for j, w in enumerate(words) if _is_number(w)]
            if nums:
                words[nums[rng.integers(len(nums))]] = TEXT_NUMBERS[rng.integers(len(TEXT_NUMBERS))]
                lines[i] = " ".join(words)
    elif kind == 1:  # a line dropped
        del lines[at]
    elif kind == 2:  # a line repeated
        lines[at:at] = [lines[at]] * int(rng.integers(1, 300))
    else:  # a keyword line inserted
        lines.insert(at, TEXT_LINES[rng.integers(len(TEXT_LINES))])
    return "\n".join(lines).encode()


def _is_number(word: str) -> bool:
    try:
        float(word)
        return True
    except ValueError:
        return False


def mutate_npz(rng: np.random.Generator, data: bytes) -> bytes:
    if rng.random() < 0.3:
        return mutate_bytes(rng, data)
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    key = sorted(arrays)[rng.integers(len(arrays))]
    a = arrays[key]
    kind = rng.integers(7)
    if kind == 0:
        del arrays[key]
    elif kind == 1:  # another dtype
        dtype = ["int8", "uint16", "bool", "complex64", "float16", "float64", "<U3", "S4"][rng.integers(8)]
        try:
            arrays[key] = a.astype(dtype)
        except (ValueError, TypeError):
            arrays[key] = np.zeros(a.shape, dtype)
    elif kind == 2:  # another shape
        arrays[key] = [
            a.reshape(-1),
            a[None],
            np.zeros((0,) + a.shape[1:], a.dtype),
            a.T,
            np.repeat(a.reshape(-1)[:1], 7),
        ][rng.integers(5)]
    elif kind == 3 and a.dtype.kind == "f" and a.size:  # extreme values
        b = a.astype(np.float64).copy()
        b.reshape(-1)[rng.integers(b.size)] = [np.nan, np.inf, 1e30, -1e30, 100.0, 1e20, -1e-45][rng.integers(7)]
        arrays[key] = b
    elif kind == 4 and a.dtype.kind == "U":  # another string
        arrays[key] = np.array(
            ["", "x" * 100_000, "[" * 2000, '{"a": NaN}', "dla.avatar/2", "\udcff"[:0] + "é"][rng.integers(6)]
        )
    elif kind == 5:
        arrays["extra_member"] = np.zeros(3)
    else:
        arrays[key] = np.array(1e300)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def mutate_ply(rng: np.random.Generator, data: bytes) -> bytes:
    """A binary .ply with one property of one vertex set to an extreme value, or a property
    dropped or turned into a list."""
    import plyfile

    if rng.random() < 0.3:
        return mutate_bytes(rng, data)
    v = plyfile.PlyData.read(io.BytesIO(data))["vertex"].data
    names = list(v.dtype.names)
    name = names[rng.integers(len(names))]
    kind = rng.integers(3)
    if kind == 0:
        v = v.copy()
        v[name][rng.integers(len(v))] = [np.nan, np.inf, 1e30, -1e30, 100.0, -100.0, 0.0, 3e38][rng.integers(8)]
        element = plyfile.PlyElement.describe(v, "vertex")
    elif kind == 1:
        keep = [n for n in names if n != name]
        element = plyfile.PlyElement.describe(
            np.array(v[keep].tolist(), dtype=[(n, v.dtype[n]) for n in keep]), "vertex"
        )
    else:
        rows = np.empty(len(v), dtype=[*((n, v.dtype[n]) for n in names if n != name), (name, object)])
        for n in names:
            rows[n] = [np.array([x, x], np.float32) for x in v[n]] if n == name else v[n]
        element = plyfile.PlyElement.describe(rows, "vertex", val_types={name: "f4"})
    buf = io.BytesIO()
    plyfile.PlyData([element], text=bool(rng.integers(2))).write(buf)
    return buf.getvalue()


def _ascii_ply(path: Path) -> bytes:
    import plyfile

    buf = io.BytesIO()
    plyfile.PlyData([plyfile.PlyData.read(str(path))["vertex"]], text=True).write(buf)
    return buf.getvalue()


MUTATORS = {"bytes": mutate_bytes, "json": mutate_json, "text": mutate_text, "npz": mutate_npz, "ply": mutate_ply}


# ---------------------------------------------------------------------------------------- seeds


def _cut_bvh(path: Path, frames: int) -> bytes:
    """A BVH file's hierarchy and its first `frames` frames."""
    head, motion = path.read_text().split("MOTION", 1)
    lines = motion.strip("\n").split("\n")
    return (head + f"MOTION\nFrames: {frames}\n{lines[1]}\n" + "\n".join(lines[2 : 2 + frames]) + "\n").encode()


def _cut_amc(path: Path, frames: int) -> bytes:
    """An AMC file's header and its first `frames` frames."""
    out, count = [], 0
    for line in path.read_text().split("\n"):
        count += line.strip().isdigit()
        if count > frames:
            break
        out.append(line)
    return ("\n".join(out) + "\n").encode()


def _photo_seeds() -> dict[str, bytes]:
    from PIL import Image

    src = Image.open(DATA / "third_party" / "images" / "pexels-marta-wave-6437749.png").convert("RGBA")
    w, h = src.size
    small = src.resize((72, round(72 * h / w)))
    kp = json.loads((DATA / "keypoints" / "pexels-marta-wave-6437749.json").read_text())
    kp["keypoints"] = [v * 72 / w if i % 3 != 2 else v for i, v in enumerate(kp["keypoints"])]
    out = {}
    for name, im in (("photo.png", small), ("mask.png", small.getchannel("A"))):
        buf = io.BytesIO()
        im.save(buf, "PNG")
        out[name] = buf.getvalue()
    out["keypoints.json"] = json.dumps(kp).encode()
    return out


def _writer_seeds(tmp: Path) -> dict:
    """Files this test writes with dla's writers (no golden file of their format exists)."""
    from dlacli.avatar.checkpoint import save_checkpoint
    from dlacli.io.ply import read_ply
    from dlacli.io.splat import write_splat
    from dlacli.io.spz import write_spz
    from dlacli.nn.discriminator import DiscriminatorConfig, PatchDiscriminator
    from dlacli.train.loop import FORMAT as TRAIN_FORMAT

    g = read_ply(EXAMPLES / "gaussians_sh3.ply")
    write_spz(g, tmp / "g.spz")
    write_splat(read_ply(EXAMPLES / "gaussians_sh0.ply"), tmp / "g.splat")
    rng = np.random.default_rng(0)
    buf = io.BytesIO()
    np.savez(
        buf,
        poses=rng.normal(0, 0.2, (4, 156)),
        trans=rng.normal(0, 0.5, (4, 3)),
        mocap_framerate=np.array(60.0),
        betas=np.zeros(16),
        gender=np.array("neutral"),
    )
    net = PatchDiscriminator(DiscriminatorConfig(base_channels=2, layers=1, max_channels=4))
    save_checkpoint(tmp / "ck", net, net.config)
    train = {
        "format": TRAIN_FORMAT,
        "settings": {"seed": 0},
        "step": 2,
        "seconds": 1.5,
        "checkpoint": "ckpt-000002",
        "history": [{"step": 1, "stage": "low", "l1": 0.5, "total": 0.7}],
        "validation": [{"step": 2, "psnr": 20.0, "psnr_masked": 18.0, "iou": 0.9}],
    }
    return {
        "g.spz": (tmp / "g.spz").read_bytes(),
        "g.splat": (tmp / "g.splat").read_bytes(),
        "amass.npz": buf.getvalue(),
        "ck": {f"ck/{f.name}": f.read_bytes() for f in sorted((tmp / "ck").iterdir())},
        "train.json": json.dumps(train).encode(),
    }


def _dataset_seed(views: dict[str, bytes]) -> dict[str, bytes]:
    """A dataset folder (formats/dataset.md) by hand: a manifest listing one subject, the example
    view folder with a `"dla": {"synth": ...}` record (no `dla synth` run)."""
    files = {f"subject_7/{rel}": data for rel, data in views.items()}
    doc = json.loads(views["transforms.json"])
    doc["dla"]["synth"] = {"seed": 7, "outfit": "suit", "appearance": "lit", "start_yaw": 12.5}
    files["subject_7/transforms.json"] = json.dumps(doc).encode()
    entry = {"seed": 7, "path": "subject_7", "outfit": "suit", "seconds": 1.5, "bytes": 1000}
    manifest = {"format": "dla.dataset/1", "settings": {"res": 8, "motion_files": []}, "subjects": [entry]}
    files["manifest.json"] = json.dumps(manifest).encode()
    return files


def targets(tmp: Path) -> list[Target]:
    from dlacli.avatar.checkpoint import checkpoint_info, load_checkpoint
    from dlacli.data.dataset import read_manifest
    from dlacli.io.amass import read_amass
    from dlacli.io.asf_amc import read_amc, read_asf, summarize_amc
    from dlacli.io.avatar import read_avatar
    from dlacli.io.body import read_body
    from dlacli.io.bvh import read_bvh
    from dlacli.io.inspect import summarize
    from dlacli.io.motion import read_motion
    from dlacli.io.photo import read_coco_keypoints, read_photo
    from dlacli.io.ply import read_ply
    from dlacli.io.splat import read_splat
    from dlacli.io.spz import read_spz
    from dlacli.io.usd_read import read_usd
    from dlacli.io.validate import load_npz
    from dlacli.io.views import read_views, view_files
    from dlacli.train.data import TrainingData
    from dlacli.train.loop import _read_record

    ex = {p.name: p.read_bytes() for p in EXAMPLES.iterdir() if p.is_file()}
    views = {str(p.relative_to(EXAMPLES / "views")): p.read_bytes() for p in (EXAMPLES / "views").rglob("*.*")}
    motion = DATA / "third_party" / "motion"
    w = _writer_seeds(tmp)

    def one(name, file, data, how, read, info=True, **kw) -> Target:
        """A one-file format: its command's reader, then (info) `dla info`'s inspect.summarize."""
        readers = [lambda d: read(d / file)] + ([lambda d: summarize(d / file)] if info else [])
        return Target(name, {file: data}, {file: how}, readers, file, **kw)

    asf_amc = {"s.asf": (motion / "cmu_01.asf").read_bytes(), "s_01.amc": _cut_amc(motion / "cmu_01_01.amc", 4)}
    amc_readers = [lambda d: read_asf(d / "s.asf"), lambda d: read_amc(d / "s_01.amc", d / "s.asf")]
    amc_readers += [lambda d: summarize_amc(d / "s_01.amc"), lambda d: summarize(d / "s.asf")]
    photo_readers = [lambda d: read_photo(d / "photo.png")]
    photo_readers += [lambda d: read_photo(d / "photo.png", d / "mask.png", d / "keypoints.json", [])]
    checkpoint_readers = [lambda d: checkpoint_info(d / "ck"), lambda d: load_checkpoint(d / "ck")]
    keypoints = (DATA / "keypoints" / "pexels-marta-wave-6437749.json").read_bytes()
    dataset_readers = [lambda d: read_manifest(d / "manifest.json"), lambda d: TrainingData(d, 4, 4, 1)]
    dataset_readers += [lambda d: TrainingData(d / "subject_7", 4, 4, 1)]
    return [
        one("ply_sh0", "g.ply", ex["gaussians_sh0.ply"], "bytes", read_ply),
        one("ply_sh3", "g.ply", ex["gaussians_sh3.ply"], "ply", read_ply),
        one("ply_ascii", "g.ply", _ascii_ply(EXAMPLES / "gaussians_sh0.ply"), "text", read_ply),
        one("spz", "g.spz", w["g.spz"], "bytes", read_spz),
        one("splat", "g.splat", w["g.splat"], "bytes", read_splat),
        one("avatar", "a.npz", ex["avatar.npz"], "npz", read_avatar),
        one("motion", "m.npz", ex["motion.npz"], "npz", read_motion),
        one("amass", "m.npz", w["amass.npz"], "npz", read_amass),
        one("amass_load", "m.npz", w["amass.npz"], "npz", load_npz, info=False),
        one("body", "body.json", ex["body.json"], "json", read_body),
        Target(
            "views",
            views,
            {"transforms.json": "json", "body.json": "json", "images/view_000.png": "bytes"},
            [read_views, view_files, summarize],
            ".",
        ),
        one("bvh", "m.bvh", _cut_bvh(motion / "131_01.bvh", 6), "text", read_bvh),
        one("bvh_cmu", "m.bvh", _cut_bvh(motion / "cmu_01_01.bvh", 4), "text", read_bvh),
        Target(
            "asf_amc", asf_amc, {"s.asf": "text", "s_01.amc": "text"}, amc_readers, "s_01.amc", agree=((0, 3), (1, 2))
        ),
        one("keypoints", "k.json", keypoints, "json", read_coco_keypoints, info=False),
        Target(
            "photo",
            _photo_seeds(),
            {"photo.png": "bytes", "mask.png": "bytes", "keypoints.json": "json"},
            photo_readers,
            agree=(),
        ),
        Target(
            "checkpoint",
            w["ck"],
            {"ck/config.json": "json", "ck/model.safetensors": "bytes"},
            checkpoint_readers,
            agree=(),
        ),
        Target("checkpoint_rehashed", w["ck"], {"ck/config.json": "json+hash"}, checkpoint_readers[1:]),
        one("train", "train.json", w["train.json"], "json", _read_record, info=False),
        Target(
            "dataset",
            _dataset_seed(views),
            {"manifest.json": "json", "subject_7/transforms.json": "json"},
            dataset_readers,
            agree=(),  # a training root also needs its subjects' folders, and a subject folder no manifest
        ),
        one("usda", "a.usda", ex["animation.usda"], "bytes", read_usd),
    ]


def _rehash(folder: Path) -> None:
    """Give a mutated config.json the content hash its weights and config now have (what an
    attacker can do: the hash is no signature), so the fuzzer reaches the network build."""
    from dlacli.avatar.checkpoint import content_hash

    try:
        rec = json.loads((folder / "ck" / "config.json").read_text())
        rec["hash"] = content_hash(
            rec["class"], rec["config_class"], rec["config"], (folder / "ck" / "model.safetensors").read_bytes()
        )
    except Exception:  # noqa: BLE001 - not hashable as it stands: leave the mutation as it is
        return
    (folder / "ck" / "config.json").write_text(json.dumps(rec))


# ------------------------------------------------------------------------------------------ runs


class Hang(BaseException):  # not an Exception: no reader's `except Exception` may swallow it
    pass


def _alarm(signum, frame):
    raise Hang(f"still reading after {SECONDS_PER_RUN:g} s")


def _snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _run(target: Target, index: int, folder: Path) -> tuple[list[str], int, int]:
    """Mutate one file of `target` into `folder` and call every reader; (problems, reader calls,
    calls that returned)."""
    rng = np.random.default_rng([SEED, index, sum(map(ord, target.name))])
    shutil.rmtree(folder, ignore_errors=True)
    for rel, data in target.files.items():
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        (folder / rel).write_bytes(data)
    rel = sorted(target.mutable)[rng.integers(len(target.mutable))]
    how = target.mutable[rel]
    (folder / rel).write_bytes(MUTATORS[how.split("+")[0]](rng, target.files[rel]))
    if how.endswith("+hash"):
        _rehash(folder)
    before = _snapshot(folder)
    problems, returned, refused = [], 0, []
    for k, read in enumerate(target.readers):
        where = f"{target.name} run {index} ({rel}, {how}) reader {k}"
        signal.setitimer(signal.ITIMER_REAL, SECONDS_PER_RUN)
        refused.append(True)
        try:
            read(folder)
            returned += 1
            refused[-1] = False
        except DlaInputError as err:
            msg = str(err)
            if "\n" in msg or "\r" in msg:
                problems.append(f"{where}: a message of several lines: {msg[:300]!r}")
            elif err.where is None or not str(err.where).startswith(str(folder)):
                problems.append(f"{where}: the message names no file of the run: {msg[:300]!r}")
            elif len(msg) - len(str(err.where)) > target.max_message:
                problems.append(f"{where}: a message of {len(msg)} characters: {msg[:300]!r}")
        except (Exception, Hang) as err:  # noqa: BLE001 - the point of the fuzzer
            frame = traceback.extract_tb(err.__traceback__)[-1]
            problems.append(
                f"{where}: {type(err).__name__}: {str(err)[:200]} (at {Path(frame.filename).name}:{frame.lineno})"
            )
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        after = _snapshot(folder)
        if after != before:
            problems.append(
                f"{where}: the reader changed or added files: {sorted(set(after.items()) ^ set(before.items()))[:3]}"
            )
    for a, b in target.agree:
        if refused[a] != refused[b]:
            problems.append(
                f"{target.name} run {index} ({rel}, {how}): reader {a % len(refused)} "
                f"{'refuses' if refused[a] else 'accepts'} what reader {b % len(refused)} "
                f"{'refuses' if refused[b] else 'accepts'}"
            )
    return problems, len(target.readers), returned


@pytest.mark.filterwarnings("error::RuntimeWarning")  # numpy's overflow warnings would reach a user's terminal
def test_every_reader_survives_the_mutations(tmp_path):
    old = signal.signal(signal.SIGALRM, _alarm)
    try:
        start, calls, problems = time.perf_counter(), 0, []
        per_target = {}
        for target in targets(tmp_path / "seeds"):
            t0, accepted = time.perf_counter(), 0
            for i in range(RUNS):
                found, n, returned = _run(target, i, tmp_path / "run")
                problems += found
                calls += n
                accepted += returned
            per_target[target.name] = f"{time.perf_counter() - t0:.1f} s, {accepted}/{n * RUNS} read"
        elapsed = time.perf_counter() - start
    finally:
        signal.signal(signal.SIGALRM, old)
    print(
        f"fuzz: {calls} reader calls over {len(per_target)} targets x {RUNS} mutations in {elapsed:.1f} s: {per_target}"
    )
    kinds = {}
    for p in problems:
        kinds.setdefault(p.split(" run ")[0] + " " + p.split(": ", 1)[1][:40], p)
    assert not problems, f"{len(problems)} problems, e.g.:\n" + "\n".join(list(kinds.values())[:40])


# ------------------------------------------------------------------------------ through the CLI


@pytest.mark.parametrize("name", ["ply_sh0", "avatar", "body", "views", "bvh", "asf_amc"])
def test_mutated_files_through_dla_info(tmp_path, name):
    """One mutated file per format that `dla info` refuses: exit code 2 and one stderr line."""
    target = next(t for t in targets(tmp_path / "seeds") if t.name == name)
    for i in range(RUNS):  # the first mutation the reader refuses
        folder = tmp_path / f"run{i}"
        _run(target, i, folder)
        try:
            target.readers[-1](folder)
        except DlaInputError:
            break
    else:
        pytest.skip(f"no mutation of {name} was refused")
    path = folder / target.info
    cmd = [sys.executable, "-c", "from dlacli.cli.app import main; main()", "info", str(path)]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert result.stdout == "" and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert result.stderr.startswith("error: ") and "Traceback" not in result.stderr
