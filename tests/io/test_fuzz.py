"""A seeded mutation fuzzer over every reader dla has (issue 20).

Seeds are the golden files of formats/examples and the third-party files of tests/data (cut short
where they are long), plus files the writers make here (.spz, .splat, AMASS, a checkpoint, a
train.json). Each run copies one seed target into a fresh folder, mutates one of its files (bit
flips, cut, inserted or repeated bytes; in JSON, a value swapped for a huge number, deep nesting,
NaN, a long string or a wrong type; in .npz, an array swapped for another dtype, shape or extreme
values; in text, numbers swapped for extreme ones and lines dropped or repeated) and calls every
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
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from dlacli.errors import DlaInputError

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "formats" / "examples"
DATA = ROOT / "tests" / "data"
SEED = 20
RUNS = 300  # mutations per target (19 targets, 2-4 readers each: ~12,000 reader calls)
SECONDS_PER_RUN = 20.0  # a reader still busy after this is a hang
MAX_MESSAGE = 300  # characters of a message beyond the file name it starts with

# raw JSON text swapped in for one value: numbers beyond float64 and Python's digit limit,
# constants JSON lacks, deep nesting, a long string, a lone surrogate, wrong types
JSON_VALUES = ["1" + "0" * 309, "9" * 5000, "NaN", "-Infinity", "1e308", "-1e-320", "0", "-1", "2147483648",
               "18446744073709551617", "true", "null", '""', json.dumps("x" * 100_000), "[]", "{}",
               "[" * 1500 + "]" * 1500, '{"a":' * 80 + "1" + "}" * 80, "[1, 2, 3]", '"\\ud800"', "0.5",
               json.dumps([[1e30] * 3] * 4), '"../../../etc/passwd"']  # fmt: skip
TEXT_NUMBERS = ["1e20", "-1e20", "1e309", "nan", "-inf", "1e-400", "0", "-0", "99999999999999999999", "7e5",
                "\u0661\u0662", "0x10", "1_000", "", "1e", "--1"]  # fmt: skip
TEXT_LINES = ["{", "}", "JOINT x", "End Site", "MOTION", "Frames: 999999999", "Frame Time: 0", ":radians",
              "ROOT", "CHANNELS 7 Xrotation", "OFFSET 1e300 0 0", "begin", "end", ":hierarchy", "root root"]  # fmt: skip


@dataclasses.dataclass
class Target:
    """A seed: its files (relative path -> bytes), which of them the fuzzer mutates and how, and
    the readers of the format, each called with the run's folder."""

    name: str
    files: dict[str, bytes]
    mutable: dict[str, str]  # relative path -> "bytes" | "json" | "text" | "npz"
    readers: list[Callable[[Path], object]]
    info: str | None = None  # the path `dla info` takes, for the CLI runs
    max_message: int | None = MAX_MESSAGE  # None: messages not bounded yet (below)
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
        arrays[key] = [a.reshape(-1), a[None], np.zeros((0,) + a.shape[1:], a.dtype), a.T,
                       np.repeat(a.reshape(-1)[:1], 7)][rng.integers(5)]  # fmt: skip
    elif kind == 3 and a.dtype.kind == "f" and a.size:  # extreme values
        b = a.astype(np.float64).copy()
        b.reshape(-1)[rng.integers(b.size)] = [np.nan, np.inf, 1e30, -1e30, 100.0, 1e20, -1e-45][rng.integers(7)]
        arrays[key] = b
    elif kind == 4 and a.dtype.kind == "U":  # another string
        arrays[key] = np.array(["", "x" * 100_000, "[" * 2000, '{"a": NaN}', "dla.avatar/2", "\udcff"[:0] + "é"][rng.integers(6)])
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
        element = plyfile.PlyElement.describe(np.array(v[keep].tolist(), dtype=[(n, v.dtype[n]) for n in keep]), "vertex")
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


def _cut_bvh(text: str, frames: int) -> str:
    head, motion = text.split("MOTION", 1)
    lines = [line for line in motion.strip("\n").split("\n")]
    return head + "MOTION\n" + f"Frames: {frames}\n" + lines[1] + "\n" + "\n".join(lines[2 : 2 + frames]) + "\n"


def _cut_amc(text: str, frames: int) -> str:
    out, count = [], 0
    for line in text.split("\n"):
        if line.strip().isdigit():
            count += 1
            if count > frames:
                break
        out.append(line)
    return "\n".join(out) + "\n"


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


def _writer_seeds(tmp: Path) -> dict[str, dict[str, bytes]]:
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
    np.savez(buf, poses=rng.normal(0, 0.2, (4, 156)), trans=rng.normal(0, 0.5, (4, 3)),
             mocap_framerate=np.array(60.0), betas=np.zeros(16), gender=np.array("neutral"))  # fmt: skip
    net = PatchDiscriminator(DiscriminatorConfig(base_channels=2, layers=1, max_channels=4))
    save_checkpoint(tmp / "ck", net, net.config)
    train = {"format": TRAIN_FORMAT, "settings": {"seed": 0}, "step": 2, "seconds": 1.5, "checkpoint": "ckpt-000002",
             "history": [{"step": 1, "stage": "low", "l1": 0.5, "total": 0.7}],
             "validation": [{"step": 2, "psnr": 20.0, "psnr_masked": 18.0, "iou": 0.9}]}  # fmt: skip
    return {
        "spz": {"g.spz": (tmp / "g.spz").read_bytes()},
        "splat": {"g.splat": (tmp / "g.splat").read_bytes()},
        "amass": {"m.npz": buf.getvalue()},
        "checkpoint": {f"ck/{f.name}": f.read_bytes() for f in sorted((tmp / "ck").iterdir())},
        "train": {"train.json": json.dumps(train).encode()},
    }


def targets(tmp: Path) -> list[Target]:
    from dlacli.avatar.checkpoint import checkpoint_info, load_checkpoint
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
    from dlacli.io.usd import read_usd
    from dlacli.io.validate import load_npz
    from dlacli.io.views import read_views, view_files
    from dlacli.train.loop import _read_record

    ex = {p.name: p.read_bytes() for p in EXAMPLES.iterdir() if p.is_file()}
    views = {str(p.relative_to(EXAMPLES / "views")): p.read_bytes() for p in (EXAMPLES / "views").rglob("*") if p.is_file()}
    motion = DATA / "third_party" / "motion"
    written = _writer_seeds(tmp)

    def info(name):  # `dla info`'s path through inspect.summarize (npz_format dispatch included)
        return lambda d: summarize(d / name)

    return [
        Target("ply_sh0", {"g.ply": ex["gaussians_sh0.ply"]}, {"g.ply": "bytes"}, [lambda d: read_ply(d / "g.ply"), info("g.ply")], "g.ply"),
        Target("ply_sh3", {"g.ply": ex["gaussians_sh3.ply"]}, {"g.ply": "ply"}, [lambda d: read_ply(d / "g.ply"), info("g.ply")]),
        Target("ply_ascii", {"g.ply": _ascii_ply(EXAMPLES / "gaussians_sh0.ply")}, {"g.ply": "text"},
               [lambda d: read_ply(d / "g.ply"), info("g.ply")]),
        Target("spz", written["spz"], {"g.spz": "bytes"}, [lambda d: read_spz(d / "g.spz"), info("g.spz")]),
        Target("splat", written["splat"], {"g.splat": "bytes"}, [lambda d: read_splat(d / "g.splat"), info("g.splat")]),
        Target("avatar", {"a.npz": ex["avatar.npz"]}, {"a.npz": "npz"}, [lambda d: read_avatar(d / "a.npz"), info("a.npz")], "a.npz"),
        Target("motion", {"m.npz": ex["motion.npz"]}, {"m.npz": "npz"}, [lambda d: read_motion(d / "m.npz"), info("m.npz")]),
        Target("amass", written["amass"], {"m.npz": "npz"},
               [lambda d: read_amass(d / "m.npz"), lambda d: load_npz(d / "m.npz"), info("m.npz")]),
        Target("body", {"body.json": ex["body.json"]}, {"body.json": "json"},
               [lambda d: read_body(d / "body.json"), info("body.json")], "body.json"),
        Target("views", views, {"transforms.json": "json", "body.json": "json", "images/view_000.png": "bytes"},
               [lambda d: read_views(d), lambda d: view_files(d), lambda d: summarize(d)], "."),
        Target("bvh", {"m.bvh": _cut_bvh((motion / "131_01.bvh").read_text(), 6).encode()}, {"m.bvh": "text"},
               [lambda d: read_bvh(d / "m.bvh"), info("m.bvh")], "m.bvh"),
        Target("bvh_cmu", {"m.bvh": _cut_bvh((motion / "cmu_01_01.bvh").read_text(), 4).encode()}, {"m.bvh": "text"},
               [lambda d: read_bvh(d / "m.bvh")]),
        Target("asf_amc", {"s.asf": (motion / "cmu_01.asf").read_bytes(),
                           "s_01.amc": _cut_amc((motion / "cmu_01_01.amc").read_text(), 4).encode()},
               {"s.asf": "text", "s_01.amc": "text"},
               [lambda d: read_asf(d / "s.asf"), lambda d: read_amc(d / "s_01.amc", d / "s.asf"),
                lambda d: summarize_amc(d / "s_01.amc"), info("s.asf")], "s_01.amc", agree=((0, 3), (1, 2))),  # fmt: skip
        Target("keypoints", {"k.json": (DATA / "keypoints" / "pexels-marta-wave-6437749.json").read_bytes()},
               {"k.json": "json"}, [lambda d: read_coco_keypoints(d / "k.json")]),
        Target("photo", _photo_seeds(), {"photo.png": "bytes", "mask.png": "bytes", "keypoints.json": "json"},
               [lambda d: read_photo(d / "photo.png"),
                lambda d: read_photo(d / "photo.png", d / "mask.png", d / "keypoints.json", [])], agree=()),  # fmt: skip
        Target("checkpoint", written["checkpoint"], {"ck/config.json": "json", "ck/model.safetensors": "bytes"},
               [lambda d: checkpoint_info(d / "ck"), lambda d: load_checkpoint(d / "ck")], agree=()),
        Target("checkpoint_rehashed", written["checkpoint"], {"ck/config.json": "json+hash"},
               [lambda d: load_checkpoint(d / "ck")]),
        Target("train", written["train"], {"train.json": "json"}, [lambda d: _read_record(d / "train.json")]),
        # pxr's parse errors quote whole attribute values (~20 KB): cutting them is io/usd.py's part of
        # issue 20 (another branch); until it lands, only their length goes unchecked here
        Target("usda", {"a.usda": ex["animation.usda"]}, {"a.usda": "bytes"}, [lambda d: read_usd(d / "a.usda"), info("a.usda")],
               max_message=None),
    ]  # fmt: skip


def _rehash(folder: Path) -> None:
    """Give a mutated config.json the content hash its weights and config now have (what an
    attacker can do: the hash is no signature), so the fuzzer reaches the network build."""
    from dlacli.avatar.checkpoint import content_hash

    try:
        rec = json.loads((folder / "ck" / "config.json").read_text())
        rec["hash"] = content_hash(rec["class"], rec["config_class"], rec["config"], (folder / "ck" / "model.safetensors").read_bytes())
    except Exception:  # noqa: BLE001 - not hashable as it stands: leave the mutation as it is
        return
    (folder / "ck" / "config.json").write_text(json.dumps(rec))


# ------------------------------------------------------------------------------------------ runs


class Hang(Exception):
    pass


def _alarm(signum, frame):
    raise Hang(f"still reading after {SECONDS_PER_RUN:g} s")


def _snapshot(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


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
            elif target.max_message is not None and len(msg) - len(str(err.where)) > target.max_message:
                problems.append(f"{where}: a message of {len(msg)} characters: {msg[:300]!r}")
        except Exception as err:  # noqa: BLE001 - the point of the fuzzer
            frame = traceback.extract_tb(err.__traceback__)[-1]
            problems.append(f"{where}: {type(err).__name__}: {str(err)[:200]} (at {Path(frame.filename).name}:{frame.lineno})")
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        after = _snapshot(folder)
        if after != before:
            problems.append(f"{where}: the reader changed or added files: {sorted(set(after.items()) ^ set(before.items()))[:3]}")
    for a, b in target.agree:
        if refused[a] != refused[b]:
            problems.append(f"{target.name} run {index} ({rel}, {how}): reader {a % len(refused)} "
                            f"{'refuses' if refused[a] else 'accepts'} what reader {b % len(refused)} "
                            f"{'refuses' if refused[b] else 'accepts'}")
    return problems, len(target.readers), returned


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
    print(f"fuzz: {calls} reader calls over {len(per_target)} targets x {RUNS} mutations in {elapsed:.1f} s: {per_target}")
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
