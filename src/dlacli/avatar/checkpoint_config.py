"""Checkpoint configs (avatar/checkpoint.py, formats/checkpoint.md): a network's Config dataclass
to and from JSON, checked field by field against its type hints, the dotted class path a checkpoint
rebuilds the network by, and the content hash over class, config and weights."""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import types
import typing

from dlacli.errors import DlaInputError, excerpt, one_line


def _canonical(obj) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False).encode("ascii")


def content_hash(class_path: str, config_class_path: str, config: dict, weights: bytes) -> str:
    """sha256 of canonical JSON {"class", "config_class", "config"}, one newline, the weights file bytes."""
    h = hashlib.sha256(_canonical({"class": class_path, "config_class": config_class_path, "config": config}))
    h.update(b"\n")
    h.update(weights)
    return h.hexdigest()


def _config_dict(obj) -> dict:
    def enc(v):
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return _config_dict(v)
        if isinstance(v, (tuple, list)):
            return [enc(x) for x in v]
        return v

    return {f.name: enc(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init}


class UnsupportedConfig(Exception):
    pass


def _type_name(hint) -> str:
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


class _BadField(DlaInputError):
    """A config field of the wrong type, its value quoted as a short excerpt."""

    def __init__(self, where, name: str, value, hint):
        super().__init__(where, f"config field {name} is {excerpt(value, 40)}, expected {_type_name(hint)}")


def _coerce(v, hint, where, name: str):
    bad = _BadField(where, name, v, hint)
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if v is None and type(None) in args:
            return None
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(v, arg, where, name)
            except DlaInputError:
                pass
        raise bad
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if not isinstance(v, dict):
            raise bad
        return config_from_dict(hint, v, where, name + ".")
    if hint in (bool, str, int, float):
        ok = (int, float) if hint is float else hint
        if not isinstance(v, ok) or (isinstance(v, bool) and hint is not bool):
            raise bad
        try:
            return hint(v)
        except OverflowError:  # an integer of hundreds of digits in a float field
            raise bad from None
    if origin in (tuple, list) and args:
        if not isinstance(v, list):
            raise bad
        if origin is list or (len(args) == 2 and args[1] is Ellipsis):
            items = [_coerce(x, args[0], where, f"{name}[{i}]") for i, x in enumerate(v)]
        elif len(v) != len(args):
            raise DlaInputError(where, f"config field {name} has {len(v)} items, expected {len(args)}")
        else:
            items = [_coerce(x, a, where, f"{name}[{i}]") for i, (x, a) in enumerate(zip(v, args))]
        return tuple(items) if origin is tuple else items
    raise UnsupportedConfig(
        f"config field {name} has type {_type_name(hint)}; checkpoints hold bool, int, float, str, "
        "None, tuple[...]/list[...] of those and nested dataclasses"
    )


def config_from_dict(cls: type, data: dict, where=None, prefix: str = ""):
    """Build the Config dataclass `cls` from its JSON object, checking every field's type;
    unknown or missing fields are a DlaInputError naming `where`."""
    older = getattr(cls, "from_older", None)  # the network's migration of configs saved before a field existed
    if callable(older):
        data = older(dict(data))
    fields = [f for f in dataclasses.fields(cls) if f.init]
    names = {f.name for f in fields}
    unknown, missing = sorted(set(data) - names), sorted(names - set(data))
    if unknown:
        raise DlaInputError(
            where,
            f"config has unknown field(s) {one_line(', '.join(prefix + n for n in unknown[:20]))} for {cls.__name__}",
        )
    if missing:
        raise DlaInputError(where, f"config lacks field(s) {', '.join(prefix + n for n in missing)} of {cls.__name__}")
    hints = typing.get_type_hints(cls)
    values = {f.name: _coerce(data[f.name], hints[f.name], where, prefix + f.name) for f in fields}
    try:
        return cls(**values)
    except (ValueError, TypeError) as err:
        raise DlaInputError(where, f"config is not a valid {cls.__name__} ({one_line(err)})") from None


def normal_config(config) -> dict:
    """The JSON object of a config, checked to rebuild an equal config (a programmer error if not)."""
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError(f"save_checkpoint: config must be a dataclass instance, not {type(config).__name__}")
    try:
        raw = json.loads(json.dumps(_config_dict(config), allow_nan=False))
        rebuilt = config_from_dict(type(config), raw, "config")
    except (TypeError, ValueError, UnsupportedConfig, DlaInputError) as err:
        raise ValueError(f"save_checkpoint: {type(config).__name__} cannot be stored as JSON: {err}") from None
    if type(config).__eq__ is not object.__eq__ and rebuilt != config:
        raise ValueError(
            f"save_checkpoint: {type(config).__name__} does not survive a JSON round trip: {config} -> {rebuilt}"
        )
    return json.loads(json.dumps(_config_dict(rebuilt)))  # ints in float fields become floats


def dotted_path(cls: type) -> str:
    path = f"{cls.__module__}.{cls.__qualname__}"
    mod = importlib.import_module(cls.__module__) if cls.__module__ != "__main__" else None
    if "." in cls.__qualname__ or getattr(mod, cls.__qualname__, None) is not cls:
        raise ValueError(f"save_checkpoint: {path} is not importable by that path; define it at the top of a module")
    return path
