"""The one registry of dream backends, the ways `dla dream --backend NAME` makes the novel views:
a name, a line for help texts, the function that makes the views and, where it needs one, the
step that loads its model first.

`views(rgb, alpha, camera, vertices, loaded, *, frames, steps, seed, say, prior)` takes the framed
photo (rgb [R, R, 3], alpha [R, R]), the crop's camera, the fitted body's vertices [V, 3] and
what `load` returned, and returns (images [4, R, R, 3], masks [4, R, R], cameras, settings to
record in the folder's dream info); view 0 is the framed photo itself. `load(model, device, res,
frames, say)` -> (what `views` needs, the model name it loaded). `prior`: the completion prior
(stages/dream/completion.py), passed to a backend with `takes_prior`; `dla dream` refuses
`--prior` for the others.

A new backend is one module of this package (its views function and its `register(Backend(...))`
line) plus its name in BUILT_IN (a test's toy registers itself). Torch-free at import: the CLI
reads the registry before it loads torch (while the person is detected).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass

from dlacli.registry import Registry

DEFAULT = "body"


@dataclass(frozen=True)
class Backend:
    name: str
    about: str  # one line for help texts
    views: Callable
    load: Callable | None = None  # loads a model before the photo is read (None: nothing to load)
    takes_prior: bool = False  # uses the completion prior (`dla dream --prior`)


BACKENDS: Registry[Backend] = Registry("backend")
register = BACKENDS.add  # add (or replace) an entry; returns it
names = BACKENDS.names


def get(name: str, where: str = "--backend") -> Backend:
    """The backend called `name`, else a one-line error listing the known ones."""
    return BACKENDS.choose(name, where)


# each a module of this package that registers itself, loaded by name (the registry imports none of them)
BUILT_IN = ("body", "shell", "diffusion")
for _name in BUILT_IN:
    importlib.import_module(f"{__name__}.{_name}")
