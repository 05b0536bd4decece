"""The one registry of lift methods: a name, a config dataclass and a lift function per method,
and the one spec syntax that `dla lift --method` and every `dla bench` suite read.

A method turns a view folder (a ViewSet with its body) into a LiftResult (avatar, unstructured
Gaussians, contact sheet). Its name is the encoder its avatars record (`Avatar.encoder`), the
`method` of every result row, and what tables and charts call it. A new method is one file (its
config dataclass, lift function and its `register(Method(...))` line, beside unproject.py, learned.py and
residual.py in this package) plus its name in `BUILT_IN` (a test's toy registers itself instead).

Spec syntax (`NAME[:KEY=VALUE[,KEY=VALUE...]]`; a list separates specs by commas, a piece that
starts with `KEY=` belonging to the spec before it):

    unproject                          mesh unprojection alone (paper ablation A.i; 0 steps)
    unproject:steps=50                 + 50 refinement steps through skinning and splatting
    unproject:steps=150,render_size=256
    unproject:steps=50,lr=0.01         the default lift before it took 30 steps at lr 0.03
    learned:checkpoint=PATH,steps=20   the learned encoder + GPD, + 20 refinement steps of Z
    residual:checkpoint=PATH,steps=10  unprojection corrected by the residual network, + 10 steps

A bare name means the config's defaults; `dla lift` alone refines by default (`lift_defaults`).
Older spellings still read: `refine` (unproject with the default lift's steps),
`refine:STEPS[@SIZE]` (unproject:steps=STEPS[,render_size=SIZE]) and `learned:CKPT[:STEPS]`
(learned:checkpoint=CKPT[,steps=STEPS]). Old result rows name methods "refine",
"unproject+refine" and "learned+refine"; `LEGACY_NAMES` maps them (bench/rows.py reads them).

Torch-free at import (the CLI builds its help from here); each lift imports its stage when run.
"""

from __future__ import annotations

import dataclasses
import importlib
import re
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from dlacli.errors import DlaInputError
from dlacli.limits import LIFT_STEPS, MAX_LIST_CHARS
from dlacli.registry import Registry

Progress = Callable[[int, float], None]  # (step index, loss) after each refinement step
LiftFn = Callable[[Any, Any, "Progress | None", Any], Any]  # (views, config, progress, novel) -> LiftResult

# result rows written before the registry: their method name -> the registry's
LEGACY_NAMES = {"refine": "unproject", "unproject+refine": "unproject", "learned+refine": "learned"}


@dataclass(frozen=True)
class Method:
    """One lift method. `config` is a dataclass whose field defaults are what the bare name
    means; a field defaulting to None means "the stage's own default" and is recorded in result
    rows only when a spec sets it. `lift(views, config, progress, novel)` -> LiftResult."""

    name: str
    config: type
    lift: LiftFn
    about: str  # one line for help texts
    lift_defaults: Mapping[str, Any] = field(default_factory=dict)  # what `dla lift` uses where a spec is silent
    install: Callable[[Any], None] | None = None  # makes its avatars decodable elsewhere (a checkpoint's cache entry)


METHODS: Registry[Method] = Registry("method", sort=True)


def register(method: Method) -> Method:
    """Add (or replace) a method; returns it."""
    if not dataclasses.is_dataclass(method.config):
        raise TypeError(f"method {method.name!r}: config must be a dataclass")
    return METHODS.add(method)


def names() -> list[str]:
    return METHODS.names()


def get(name: str, where: str = "--method") -> Method:
    """The method called `name`, else a one-line error listing the known ones."""
    return METHODS.choose(name, where)


@dataclass(frozen=True)
class MethodSpec:
    """A method with its config, as a spec chose it. `label` is the spec as written; `given` the
    config fields it set (the rest are the config's defaults)."""

    method: Method
    config: Any
    label: str
    given: frozenset = frozenset()

    @property
    def name(self) -> str:
        return self.method.name

    def options(self) -> dict:
        """The config as a result row records it: every field that is not None."""
        return {k: v for k, v in dataclasses.asdict(self.config).items() if v is not None}

    def with_options(self, where: str = "method", **values) -> MethodSpec:
        """This spec with more fields set (one-line error for a field the method does not take)."""
        return _build(self.method, {**{k: getattr(self.config, k) for k in self.given}, **values}, self.label, where)

    def lift(self, views, progress: Progress | None = None, novel=None):
        """views (ViewSet with body) -> LiftResult; `novel`: ground-truth views for the contact sheet."""
        return self.method.lift(views, self.config, progress, novel)

    def install(self) -> None:
        """Make the avatars this spec lifts decodable by other commands (`Method.install`)."""
        if self.method.install is not None:
            self.method.install(self.config)


# ------------------------------------------------------------------------------ parsing

_KEY = re.compile(r"[a-z_][a-z0-9_]*=")


def _value(text: str, kind) -> Any:
    """A spec's text value as the field's type (int, float, bool, str; Optional of those)."""
    args = [a for a in typing.get_args(kind) if a is not type(None)]
    kind = args[0] if args else kind
    if kind is bool:
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"expected true or false, got {text[:40]!r}")
    try:
        return kind(text)
    except ValueError:
        raise ValueError(f"expected {'an integer' if kind is int else 'a number'}, got {text[:40]!r}") from None


def _build(method: Method, values: dict, label: str, where: str, flags: Mapping[str, str] = {}) -> MethodSpec:
    hints = typing.get_type_hints(method.config)
    unknown = [k for k in values if k not in hints]
    if unknown:
        raise DlaInputError(where, f"{label[:80]}: {method.name} takes no {unknown[0]!r} (it takes {', '.join(hints)})")
    try:
        typed = {}
        for key, v in values.items():
            try:
                typed[key] = _value(v, hints[key]) if isinstance(v, str) and hints[key] is not str else v
            except ValueError as err:
                raise ValueError(f"{key}: {err}") from None
        config = method.config(**typed)
    except Missing as err:
        flag = flags.get(err.key)
        raise DlaInputError(
            flag or where, f"{label[:80]}: needs {err.key}=..." + (f" or {flag}" if flag else "") + f" ({err.what})"
        ) from None
    except (TypeError, ValueError) as err:
        raise DlaInputError(where, f"{label[:80]}: {err}") from None
    return MethodSpec(method, config, label, frozenset(values))


def _legacy(name: str, rest: str, refine_steps: int) -> tuple[str, dict] | None:
    """The older spellings (module doc) -> (method name, options); None when `name:rest` is not one.
    A bare `refine` refines `refine_steps` steps (`dla bench stability --steps`, default LIFT_STEPS)."""
    if name == "refine":
        if not rest:
            return "unproject", {"steps": refine_steps}
        steps, _, size = rest.partition("@")
        if not steps.isdigit() or not (size.isdigit() or not size):
            raise ValueError("expected refine:STEPS[@SIZE]")
        if int(steps) < 1:
            raise ValueError("refine takes at least 1 step (unproject is the 0-step method)")
        return "unproject", {"steps": int(steps), **({"render_size": int(size)} if size else {})}
    if name == "learned" and rest and not _KEY.match(rest):
        head, _, tail = rest.rpartition(":")
        ckpt, steps = (head, int(tail)) if head and tail.isdigit() else (rest, 0)
        return "learned", {"checkpoint": ckpt, "steps": steps}
    return None


def _one(text: str, where: str, refine_steps: int, fill: Mapping[str, Any], flags: Mapping[str, str]) -> MethodSpec:
    name, _, rest = text.partition(":")
    try:
        old = _legacy(name, rest, refine_steps)
    except ValueError as err:
        raise DlaInputError(where, f"cannot read {text[:80]!r}: {err}") from None
    method = get(old[0] if old is not None else name, where)
    values: dict[str, Any] = dict(old[1]) if old is not None else {}
    for pair in rest.split(",") if rest and old is None else []:
        if not _KEY.match(pair):
            raise DlaInputError(where, f"cannot read {text[:80]!r}: expected NAME[:KEY=VALUE,...]")
        key, _, value = pair.partition("=")
        if key in values:
            raise DlaInputError(where, f"{text[:80]}: {key} is given twice")
        values[key] = value
    fields = {f.name for f in dataclasses.fields(method.config)}
    values.update({k: v for k, v in fill.items() if k in fields and k not in values})
    return _build(method, values, text, where, flags)


def parse_methods(
    text: str,
    where: str = "--methods",
    *,
    refine_steps: int = LIFT_STEPS,
    fill: Mapping[str, Any] | None = None,
    flags: Mapping[str, str] | None = None,
) -> list[MethodSpec]:
    """A comma-separated list of specs (module doc) -> MethodSpecs; one-line errors naming the
    bad spec. `refine_steps`: what the older bare spelling `refine` refines; `fill`: options
    (from a command's own flags, e.g. a checkpoint) for every spec whose method takes them and
    that does not set them itself; `flags`: the flag that sets a field, named when it is missing."""
    if len(text) > MAX_LIST_CHARS:
        raise DlaInputError(where, "is too long")
    pieces = [p.strip() for p in text.split(",") if p.strip()]
    specs: list[str] = []
    for piece in pieces:
        if _KEY.match(piece) and specs and ":" in specs[-1]:
            specs[-1] += "," + piece
        else:
            specs.append(piece)
    if not specs:
        raise DlaInputError(where, "is empty")
    return [_one(s, where, refine_steps, fill or {}, flags or {}) for s in specs]


def parse_method(text: str, where: str = "--method", **how) -> MethodSpec:
    """Exactly one spec (`parse_methods`, with its keyword options `how`)."""
    specs = parse_methods(text, where, **how)
    if len(specs) != 1:
        raise DlaInputError(where, f"expected one method, got {len(specs)}")
    return specs[0]


def make_spec(name: str, where: str = "method", **options) -> MethodSpec:
    """The spec of method `name` with these options (values of the config's types)."""
    label = name + (":" + ",".join(f"{k}={v}" for k, v in options.items()) if options else "")
    return _build(get(name, where), options, label, where)


# ------------------------------------------------------------------------------ what configs share


def check(ok: bool, message: str) -> None:
    """A config's bound: a ValueError that `_build` turns into a one-line error naming the spec."""
    if not ok:
        raise ValueError(message)


def check_range(name: str, value, low, high) -> None:
    """`value` (None: the stage's default, always allowed) must lie in [low, high]."""
    check(value is None or low <= value <= high, f"{name} must be in [{low}, {high}], got {value}")


class Missing(ValueError):
    """A config field a spec must set (`_build` names the flag that can set it, where there is one)."""

    def __init__(self, key: str, what: str):
        super().__init__(f"needs {key}=... ({what})")
        self.key, self.what = key, what


# ------------------------------------------------------------------------------ the built-in methods

# each is a module of this package that registers itself (config, lift, install: one file per
# method); loaded by name, so that the registry imports none of them and they import the registry
BUILT_IN = ("unproject", "learned", "residual")
for _name in BUILT_IN:
    importlib.import_module(f"{__name__}.{_name}")
