"""Network checkpoints: safetensors weights + a JSON config that rebuilds the module alone.

A network is a `@dataclass` Config and an `nn.Module` built as `Net(config)` (nanoGPT's
GPTConfig/GPT); its checkpoint is a folder (formats/checkpoint.md):

    config.json           {"format": "dla.checkpoint/1", "class", "config_class", "config", "step", "hash", ...}
    model.safetensors     the state_dict (tied tensors stored once)
    optimizer.safetensors optional: the optimizer state's tensors (its other state is in config.json)

`hash` is the sha256 of the network (class, config class, config, weights file), not of the
training state, so the same weights always get the same hash; `load_checkpoint` recomputes it
from what it read. The loader imports classes only from inside `dlacli.` (a checkpoint must not
be able to run arbitrary code) and never unpickles anything.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import math
import os
import re
import shutil
import struct
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import torch
from torch import nn

# a config's JSON, its checks and the content hash (config_from_dict and content_hash re-exported)
from dlacli.avatar.checkpoint_config import UnsupportedConfig, dotted_path, normal_config
from dlacli.avatar.checkpoint_config import config_from_dict as config_from_dict
from dlacli.avatar.checkpoint_config import content_hash as content_hash
from dlacli.errors import DlaInputError, excerpt, one_line
from dlacli.io.atomic import atomic_dir, check_outputs
from dlacli.io.files import MAX_BINARY_BYTES, MAX_JSON_BYTES, read_bytes
from dlacli.io.validate import parse_json
from dlacli.paths import checkpoints_dir

FORMAT = "dla.checkpoint/1"
CONFIG, WEIGHTS, OPTIMIZER = "config.json", "model.safetensors", "optimizer.safetensors"
FILES = (CONFIG, WEIGHTS, OPTIMIZER)
ALLOWED_PREFIXES = ("dlacli.",)
ID_CHARS = 16  # short id shown to people: the first 16 hex digits of the hash
MIN_PREFIX = 6  # shortest hash prefix the resolver accepts
_KEYS = {"format", "class", "config_class", "config", "step", "hash", "optimizer", "extra"}
_HEX = re.compile(r"[0-9a-f]{64}")
_DOTTED = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)+")


@dataclasses.dataclass
class Loaded:
    module: nn.Module  # in eval mode, on map_location
    config: Any  # the Config dataclass instance
    step: int
    hash: str  # 64 lower-case hex digits
    optimizer_state: dict | None  # ready for `optimizer.load_state_dict`, or None
    extra: dict
    path: Path


@dataclasses.dataclass
class Info:  # what config.json says, read without importing anything
    path: Path
    class_path: str
    config_class_path: str
    config: dict
    step: int
    hash: str
    optimizer: dict | None
    extra: dict


def short_id(digest: str) -> str:
    return digest[:ID_CHARS]


# --------------------------------------------------------------------------------------------
# optimizer state: tensors to safetensors, the rest to JSON (tuples, int keys, inf kept exactly)


def _encode_state(obj, tensors: dict, path: str):
    if isinstance(obj, torch.Tensor):
        name = path if path not in tensors else f"{path}#{len(tensors)}"
        tensors[name] = obj.detach().to("cpu").contiguous()
        return {"$tensor": name}
    if isinstance(obj, float) and not math.isfinite(obj):
        return {"$float": repr(obj)}
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    if isinstance(obj, tuple):
        return {"$tuple": [_encode_state(v, tensors, f"{path}.{i}") for i, v in enumerate(obj)]}
    if isinstance(obj, list):
        return [_encode_state(v, tensors, f"{path}.{i}") for i, v in enumerate(obj)]
    if isinstance(obj, dict):
        if all(isinstance(k, str) and not k.startswith("$") for k in obj):
            return {k: _encode_state(v, tensors, f"{path}.{k}") for k, v in obj.items()}
        return {
            "$items": [
                [_encode_state(k, tensors, path), _encode_state(v, tensors, f"{path}.{k}")] for k, v in obj.items()
            ]
        }
    raise TypeError(
        f"save_checkpoint: optimizer state holds a {type(obj).__name__} at {path}; cannot store it without pickle"
    )


def _decode_state(obj, tensors: dict, where):
    if isinstance(obj, list):
        return [_decode_state(v, tensors, where) for v in obj]
    if not isinstance(obj, dict):
        return obj
    if len(obj) == 1 and next(iter(obj)).startswith("$"):
        ((tag, v),) = obj.items()
        if tag == "$tensor" and isinstance(v, str) and v in tensors:
            return tensors[v]
        if tag == "$float" and v in ("inf", "-inf", "nan"):
            return float(v)
        if tag == "$tuple" and isinstance(v, list):
            return tuple(_decode_state(x, tensors, where) for x in v)
        if tag == "$items" and isinstance(v, list) and all(isinstance(kv, list) and len(kv) == 2 for kv in v):
            try:
                return {_decode_state(k, tensors, where): _decode_state(x, tensors, where) for k, x in v}
            except TypeError:  # an unhashable key
                pass
        raise DlaInputError(where, f"optimizer state has a malformed {tag} entry")
    return {k: _decode_state(v, tensors, where) for k, v in obj.items()}


# --------------------------------------------------------------------------------------------
# weights


def _aliases(state: dict[str, torch.Tensor]) -> dict[str, str]:
    """{alias: kept name} for state_dict entries that are the same tensor (tied weights)."""
    seen, out = {}, {}
    for name, t in state.items():
        if t.numel() == 0:
            continue
        key = (t.untyped_storage().data_ptr(), t.storage_offset(), tuple(t.shape), t.stride(), t.dtype, t.device)
        if key in seen:
            out[name] = seen[key]
        else:
            seen[key] = name
    return out


def _weights_bytes(module: nn.Module) -> bytes:
    from safetensors.torch import save

    state = module.state_dict()
    aliases = _aliases(state)
    tensors, storages = {}, set()
    for name, t in ((k, v.detach().to("cpu").contiguous()) for k, v in state.items() if k not in aliases):
        if t.numel() and t.untyped_storage().data_ptr() in storages:
            t = t.clone()  # a partial view of another entry: store a copy (safetensors refuses shared storage)
        storages.add(t.untyped_storage().data_ptr())
        tensors[name] = t
    return save(tensors)


def _check_sizes(data: bytes, where) -> None:
    """A safetensors file shorter than its header says is truncated (named before any hash check)."""
    if len(data) < 8:
        raise DlaInputError(where, f"truncated: {len(data)} bytes, not a safetensors file")
    (n,) = struct.unpack("<Q", data[:8])
    if 8 + n > len(data):
        raise DlaInputError(where, f"truncated: {len(data)} bytes, its header alone needs {8 + n}")
    header = parse_json(data[8 : 8 + n], where, "its header", constants=False)
    if not isinstance(header, dict):
        raise DlaInputError(where, "not a safetensors file (its header is not a JSON object)")
    ends = [
        e["data_offsets"][-1]
        for k, e in header.items()
        if k != "__metadata__"
        and isinstance(e, dict)
        and isinstance(e.get("data_offsets"), list)
        and e["data_offsets"]
        and isinstance(e["data_offsets"][-1], int)
    ]
    need = 8 + n + max(ends, default=0)
    if len(data) < need:
        raise DlaInputError(where, f"truncated: {len(data)} bytes, its header describes {need}")


def _safetensors(data: bytes, where) -> dict[str, torch.Tensor]:
    """Tensors of a safetensors file's bytes; a truncated or malformed file is a DlaInputError."""
    from safetensors.torch import load

    _check_sizes(data, where)
    try:
        return load(data)
    except Exception as err:  # SafetensorError has no stable public base class
        raise DlaInputError(where, f"not a readable safetensors file ({one_line(err)})") from None


# --------------------------------------------------------------------------------------------
# save


def save_checkpoint(
    path, module: nn.Module, config, *, step: int = 0, optimizer=None, extra: dict | None = None
) -> str:
    """Write the checkpoint folder `path` atomically; return its content hash (64 hex digits).

    module is rebuilt at load time as `type(module)(config)`; optimizer (any torch optimizer) is
    saved for resuming training; extra is any JSON object (provenance, losses), not hashed."""
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise ValueError(f"save_checkpoint: step must be an int >= 0, not {step!r}")
    class_path, config_class_path = dotted_path(type(module)), dotted_path(type(config))
    config_json = normal_config(config)
    weights = _weights_bytes(module)
    digest = content_hash(class_path, config_class_path, config_json, weights)
    record = {
        "format": FORMAT,
        "class": class_path,
        "config_class": config_class_path,
        "config": config_json,
        "step": step,
        "hash": digest,
        "optimizer": None,
        "extra": dict(extra or {}),
    }
    opt_bytes = None
    if optimizer is not None:
        from safetensors.torch import save

        tensors: dict[str, torch.Tensor] = {}
        state = _encode_state(optimizer.state_dict(), tensors, "opt")
        opt_bytes = save(tensors)
        record["optimizer"] = {
            "class": f"{type(optimizer).__module__}.{type(optimizer).__qualname__}",
            "sha256": hashlib.sha256(opt_bytes).hexdigest(),
            "state": state,
        }
    try:
        text = json.dumps(record, indent=2, allow_nan=False) + "\n"
    except (TypeError, ValueError) as err:
        raise ValueError(f"save_checkpoint: extra is not plain JSON ({err})") from None
    check_outputs(folders=[(path, FILES)])
    with atomic_dir(path) as tmp:
        (tmp / WEIGHTS).write_bytes(weights)
        if opt_bytes is not None:
            (tmp / OPTIMIZER).write_bytes(opt_bytes)
        (tmp / CONFIG).write_text(text, encoding="utf-8")
    return digest


# --------------------------------------------------------------------------------------------
# read and load


def _folder(path) -> Path:
    path = Path(path)
    return path.parent if path.name in FILES and path.is_file() else path


def _read_record(folder: Path) -> dict:
    where = folder / CONFIG
    if not folder.exists():
        raise DlaInputError(folder, "no such checkpoint folder")
    if not folder.is_dir():
        raise DlaInputError(folder, f"not a checkpoint folder (expected a folder holding {CONFIG} and {WEIGHTS})")
    rec = parse_json(read_bytes(where, MAX_JSON_BYTES), where, constants=False)
    if not isinstance(rec, dict):
        raise DlaInputError(where, "must be a JSON object")
    fmt = rec.get("format")
    if fmt != FORMAT:
        what = f"format {excerpt(fmt)}" if fmt is not None else "no 'format' key"
        raise DlaInputError(where, f"{what}; dla reads {FORMAT!r} checkpoints")
    if unknown := sorted(set(rec) - _KEYS):
        keys = one_line(", ".join(unknown[:20]))
        raise DlaInputError(where, f"unknown key(s) {keys} (put project data under 'extra')")
    for key, kind in (("class", str), ("config_class", str), ("config", dict), ("step", int), ("hash", str)):
        if key not in rec:
            raise DlaInputError(where, f"lacks the key {key!r}")
        if not isinstance(rec[key], kind) or isinstance(rec[key], bool) or (key == "step" and rec[key] < 0):
            raise DlaInputError(
                where,
                f"{key!r} must be a JSON {'object' if kind is dict else kind.__name__}"
                f"{' >= 0' if key == 'step' else ''}",
            )
    if not _HEX.fullmatch(rec["hash"]):
        raise DlaInputError(where, f"hash {excerpt(rec['hash'])} is not 64 lower-case hex digits")
    opt = rec.get("optimizer")
    if opt is not None and not (isinstance(opt, dict) and isinstance(opt.get("sha256"), str) and "state" in opt):
        raise DlaInputError(where, "'optimizer' must be null or an object with 'sha256' and 'state'")
    if not isinstance(rec.get("extra", {}), dict):
        raise DlaInputError(where, "'extra' must be a JSON object")
    return rec


def _verified_weights(folder: Path, rec: dict) -> bytes:
    weights_path = folder / WEIGHTS
    weights = read_bytes(weights_path, MAX_BINARY_BYTES)
    _check_sizes(weights, weights_path)
    got = content_hash(rec["class"], rec["config_class"], rec["config"], weights)
    if got != rec["hash"]:
        raise DlaInputError(
            folder,
            f"content hash {short_id(got)}... differs from the recorded {short_id(rec['hash'])}...: "
            f"{WEIGHTS} or the config was changed or damaged",
        )
    return weights


def checkpoint_info(path, *, verify: bool = True) -> Info:
    """Read config.json (and, with verify, check the weights' and optimizer's hashes); imports nothing."""
    folder = _folder(path)
    rec = _read_record(folder)
    if verify:
        _verified_weights(folder, rec)
        if rec.get("optimizer") is not None:
            _optimizer_tensors(folder, rec["optimizer"])
    return Info(
        folder,
        rec["class"],
        rec["config_class"],
        rec["config"],
        rec["step"],
        rec["hash"],
        rec.get("optimizer"),
        rec.get("extra", {}),
    )


def _optimizer_tensors(folder: Path, opt: dict) -> dict[str, torch.Tensor]:
    data = read_bytes(folder / OPTIMIZER, MAX_BINARY_BYTES)
    if hashlib.sha256(data).hexdigest() != opt["sha256"]:
        raise DlaInputError(
            folder / OPTIMIZER, f"sha256 differs from the one {CONFIG} records: the file was changed or damaged"
        )
    return _safetensors(data, folder / OPTIMIZER)


def _inside(module_name: str, allowed: tuple[str, ...]) -> bool:
    return any((module_name + ".").startswith(p if p.endswith(".") else p + ".") for p in allowed)


def _check_path(dotted: str, what: str, where, allowed: tuple[str, ...]) -> None:
    if not _DOTTED.fullmatch(dotted):
        raise DlaInputError(where, f"{what} {excerpt(dotted)} is not a dotted Python path")
    if not _inside(dotted.rsplit(".", 1)[0], allowed):
        raise DlaInputError(
            where,
            f"{what} {excerpt(dotted)} is outside {', '.join(allowed)}; dla imports checkpoint classes only from there",
        )


def _import(dotted: str, what: str, where, allowed: tuple[str, ...]):
    mod_name, attr = dotted.rsplit(".", 1)
    try:
        mod = importlib.import_module(mod_name)
    except ImportError as err:
        raise DlaInputError(
            where, f"{what} {excerpt(dotted)} cannot be imported ({one_line(err)}); is this dla version too old?"
        ) from None
    obj = getattr(mod, attr, None)
    if not isinstance(obj, type):
        raise DlaInputError(where, f"{what} {excerpt(dotted)} does not exist in this dla version")
    if not _inside(obj.__module__, allowed):  # a name a dlacli module imported from elsewhere
        problem = f"{what} {excerpt(dotted)} is defined in {obj.__module__}"
        raise DlaInputError(where, f"{problem}, outside {', '.join(allowed)}")
    return obj


def load_checkpoint(path, *, map_location="cpu", allowed_prefixes: Iterable[str] = ALLOWED_PREFIXES) -> Loaded:
    """Rebuild the network of a checkpoint folder from its config alone, load its weights
    (strictly) and check its hash. Every problem is a one-line DlaInputError naming the file."""
    folder = _folder(path)
    rec = _read_record(folder)
    where = folder / CONFIG
    allowed = tuple(allowed_prefixes)
    _check_path(rec["class"], "class", where, allowed)  # both before importing either
    _check_path(rec["config_class"], "config_class", where, allowed)
    cls, config_cls = (
        _import(rec["class"], "class", where, allowed),
        _import(rec["config_class"], "config_class", where, allowed),
    )
    if not issubclass(cls, nn.Module):
        raise DlaInputError(where, f"class {rec['class']!r} is not a torch nn.Module")
    if not dataclasses.is_dataclass(config_cls):
        raise DlaInputError(where, f"config_class {rec['config_class']!r} is not a dataclass")
    try:
        config = config_from_dict(config_cls, rec["config"], where)
    except UnsupportedConfig as err:
        raise DlaInputError(where, str(err)) from None
    weights = _verified_weights(folder, rec)
    tensors = _safetensors(weights, folder / WEIGHTS)
    _check_size(cls, config, len(weights), where)
    try:
        module = cls(config)
    except (ValueError, TypeError, RuntimeError) as err:
        raise DlaInputError(where, f"config does not build {cls.__name__} ({one_line(err)})") from None
    expected = module.state_dict()
    aliases = _aliases(expected)
    want = {k: tuple(t.shape) for k, t in expected.items() if k not in aliases}
    missing, unexpected = sorted(set(want) - set(tensors)), sorted(set(tensors) - set(want))
    wrong = [
        f"{k} {tuple(tensors[k].shape)} vs {want[k]}"
        for k in want
        if k in tensors and tuple(tensors[k].shape) != want[k]
    ]
    for label, items in (
        ("lacks", missing),
        ("has unexpected", unexpected),
        ("has wrong shapes (file vs network)", wrong),
    ):
        if items:
            more = f", ... ({len(items)} in all)" if len(items) > 3 else ""
            raise DlaInputError(folder / WEIGHTS, f"{label} tensors for {cls.__name__}: {', '.join(items[:3])}{more}")
    state = dict(tensors)
    state.update({alias: tensors[kept] for alias, kept in aliases.items()})
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise DlaInputError(folder / WEIGHTS, " ".join(str(err).split())[:300]) from None
    module.to(map_location).eval()
    optimizer_state = None
    if rec.get("optimizer") is not None:
        opt_tensors = {k: v.to(map_location) for k, v in _optimizer_tensors(folder, rec["optimizer"]).items()}
        optimizer_state = _decode_state(rec["optimizer"]["state"], opt_tensors, where)
    return Loaded(module, config, rec["step"], rec["hash"], optimizer_state, rec.get("extra", {}), folder)


UNSAVED_BYTES = 256 * 2**20  # what a network may hold beyond its weights file (buffers it does not save)


def _check_size(cls: type, config, weight_bytes: int, where) -> None:
    """Refuse a config that would build a network far larger than its weights file (a config.json
    whose hash was recomputed after its sizes were raised to billions) before anything is
    allocated: the network is built on the meta device first, which allocates nothing. A network
    that cannot be built on meta is left to the real build."""
    try:
        with torch.device("meta"):
            skeleton = cls(config)
        tensors = [*skeleton.parameters(), *skeleton.buffers()]  # shared (tied) tensors once
        size = sum(t.numel() * t.element_size() for t in tensors if t.is_meta)
    except Exception:  # noqa: BLE001 - any failure here is the real build's to report
        return
    if size > weight_bytes + UNSAVED_BYTES:
        problem = f"config builds a {cls.__name__} of {size:,} bytes, far more than the {weight_bytes:,} bytes"
        raise DlaInputError(where, f"{problem} of {WEIGHTS}")


# --------------------------------------------------------------------------------------------
# resolve and install


def _candidates(root: Path) -> list[Path]:
    if (root / CONFIG).is_file():
        return [root]
    try:
        return sorted(p for p in root.iterdir() if (p / CONFIG).is_file())
    except OSError:
        return []


def resolve_checkpoint(hash_or_path, *, search: Iterable[str | os.PathLike] | None = None) -> Path:
    """A path that exists, as is; otherwise the checkpoint whose recorded hash is `hash_or_path`
    (full, or a prefix of >= 6 hex digits that only one hash has), looked up in the `search`
    folders (each a checkpoint or a folder of checkpoints) and then in the cache folder."""
    text = os.fspath(hash_or_path)
    if os.path.lexists(text):
        return Path(text)
    prefix = text.strip().lower()
    if not re.fullmatch(f"[0-9a-f]{{{MIN_PREFIX},64}}", prefix):
        raise DlaInputError(text, f"no such file or folder, and not a checkpoint hash ({MIN_PREFIX} to 64 hex digits)")
    roots = [Path(s) for s in (search or ())] + [checkpoints_dir()]
    found: dict[str, Path] = {}
    for root in roots:
        for cand in _candidates(root):
            try:
                digest = _read_record(cand)["hash"]
            except DlaInputError:
                continue  # a damaged checkpoint elsewhere does not hide the others
            if digest.startswith(prefix):
                found.setdefault(digest, cand)
    if len(found) > 1:
        listed = "; ".join(f"{short_id(d)} ({p})" for d, p in sorted(found.items())[:5])
        raise DlaInputError(
            f"checkpoint {prefix}", f"prefix is ambiguous, it matches {len(found)}: {listed}; give more digits"
        )
    if not found:
        where = ", ".join(str(r) for r in roots)
        raise DlaInputError(
            f"checkpoint {prefix}",
            f"not found in {where}; pass --checkpoint PATH, or copy the checkpoint folder into {roots[-1]}",
        )
    return next(iter(found.values()))


def install_checkpoint(path) -> Path:
    """Verify a checkpoint and copy it into the cache folder as `<cache>/checkpoints/<hash>/`."""
    info = checkpoint_info(path, verify=True)
    dest = checkpoints_dir() / info.hash
    present = [name for name in FILES if (info.path / name).is_file()]
    if dest.is_dir() and all((dest / name).is_file() for name in present):
        try:
            if checkpoint_info(dest, verify=True).hash == info.hash:
                return dest  # already installed
        except DlaInputError:
            pass  # a damaged copy: replace it
    with atomic_dir(dest) as tmp:
        for name in present:
            shutil.copyfile(info.path / name, tmp / name)
    return dest
