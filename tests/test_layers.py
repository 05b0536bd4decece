"""The layering of docs/architecture.md ("The layers"), checked on the source with `ast` (every import, at any
depth: module level, inside functions, under `if TYPE_CHECKING:`), plus the start-up promise that
`dla --version` and `dla info` on the small artifacts never load torch.

Direction (an import may only point to a lower rank, or stay inside its own unit):

    errors, paths, the package  <-  types, kernel_path, registry  <-  geometry, kinematics, triangle_kernels
        <-  body, render, io  <-  avatar  <-  nn  <-  data, stages  <-  train, bench  <-  cli

body, render and io are one level and do not import each other, nor do data and stages; `ALLOWED`
lists the edges within a level that the code has a reason for. Nothing imports `dlacli.cli` but `dlacli.cli`.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "dlacli"
EXAMPLES = Path(__file__).resolve().parents[1] / "formats" / "examples"

# unit -> rank. A unit is a top-level module (dlacli.types) or a subpackage (dlacli.io).
RANK = {
    "dlacli": 0,  # the package itself (__version__)
    "dlacli.errors": 0,
    "dlacli.paths": 0,
    "dlacli.limits": 0,
    "dlacli.types": 1,
    "dlacli.kernel_path": 1,
    "dlacli.registry": 1,
    "dlacli.geometry": 2,
    "dlacli.kinematics": 2,
    "dlacli.triangle_kernels": 2,
    "dlacli.body": 3,
    "dlacli.render": 3,
    "dlacli.io": 3,
    "dlacli.avatar": 4,
    "dlacli.nn": 5,
    "dlacli.data": 6,  # synthetic subjects and datasets, beside the stages
    "dlacli.stages": 6,
    "dlacli.train": 7,
    "dlacli.bench": 7,
    "dlacli.cli": 8,
}

# (importer, imported) pairs allowed between two units of the same rank, with the reason.
ALLOWED = {
    ("dlacli.body.uv", "dlacli.io.atomic"): (
        "body writes its UV-raster cache with the toolkit's one atomic writer (docs/architecture.md, Writing files); "
        "io.atomic is a leaf of io (it imports only errors and io.files)"
    ),
    ("dlacli.data.poses", "dlacli.stages.motion.source"): (
        "synthetic target poses take frames of motion clips loaded and retargeted as `dla animate` loads them; "
        "data -> stages is the one direction between the two (no stage imports dlacli.data)"
    ),
}

# heavy or optional third-party packages -> the modules that may import them (lazily).
# bpy is used by the Blender checks in tests only, so no module under src imports it.
HEAVY = {
    "anny": {"dlacli.body.model"},
    "warp": {"dlacli.body.model"},
    "gsplat": {"dlacli.render.splat"},
    "pxr": {
        "dlacli.io.usd",
        "dlacli.io.usd_read",
        "dlacli.io.usd_rig",
    },  # the animation (write, read) and the rigged asset
    "diffusers": {"dlacli.nn.video_diffusion"},
    "mediapipe": {"dlacli.io.detect"},
    "bpy": set(),
}


@dataclass(frozen=True)
class Edge:
    importer: str  # dotted module name
    target: str  # dotted module name imported (a dlacli submodule where `from X import sub`)
    line: int
    lazy: bool  # inside a function (or class) body, not run when the module is imported

    def where(self) -> str:
        return f"{self.importer} line {self.line}: imports {self.target}"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _resolve_from(node: ast.ImportFrom, importer: str, is_package: bool) -> list[str]:
    if node.level:
        base = importer.split(".")
        if not is_package:
            base = base[:-1]
        base = base[: len(base) - (node.level - 1)]
        module = ".".join(base + ([node.module] if node.module else []))
    else:
        module = node.module or ""
    out = []
    for alias in node.names:
        sub = f"{module}.{alias.name}"
        out.append(sub if sub in MODULES else module)  # `from dlacli import geometry` -> the module
    return out


def _edges(name: str, path: Path) -> list[Edge]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    edges: list[Edge] = []

    def visit(node: ast.AST, lazy: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = lazy or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef))
            if isinstance(child, ast.Import):
                edges.extend(Edge(name, a.name, child.lineno, lazy) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                targets = _resolve_from(child, name, path.name == "__init__.py")
                edges.extend(Edge(name, t, child.lineno, lazy) for t in targets)
            visit(child, inner)

    visit(tree, False)
    return edges


EDGES = [e for name, path in MODULES.items() for e in _edges(name, path)]


def _unit(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2])  # dlacli, dlacli.types, dlacli.io (for dlacli.io.bvh)


def test_the_scan_sees_the_package():
    assert {"dlacli.types", "dlacli.io.bvh", "dlacli.cli.app", "dlacli.stages.lift.unproject"} <= set(MODULES)
    lazy = [
        e
        for e in EDGES
        if e.importer == "dlacli.stages.lift.methods.unproject" and e.target == "dlacli.stages.lift.unproject"
    ]
    assert lazy and all(e.lazy for e in lazy), lazy  # imports inside functions are seen, as lazy


def test_every_module_has_a_layer():
    missing = sorted({_unit(m) for m in MODULES} - set(RANK))
    assert not missing, f"modules outside every layer (add them to RANK, docs/architecture.md: The layers): {missing}"


def test_imports_point_down_the_layers():
    bad, used = [], set()
    for e in EDGES:
        if not (e.target == "dlacli" or e.target.startswith("dlacli.")):
            continue
        src, dst = _unit(e.importer), _unit(e.target)
        if src == dst:
            continue
        if RANK[dst] < RANK[src]:
            continue
        key = (e.importer, e.target)
        if RANK[dst] == RANK[src] and key in ALLOWED:
            used.add(key)
            continue
        rel = "a higher layer than" if RANK[dst] > RANK[src] else "the same layer as"
        bad.append(f"{e.where()} ({dst} is on {rel} {src})")
    assert not bad, "imports against the direction of docs/architecture.md's layers:\n" + "\n".join(bad)
    assert used == set(ALLOWED), f"ALLOWED lists edges the code no longer has: {set(ALLOWED) - used}"


def test_nothing_imports_the_cli():
    bad = [
        e.where()
        for e in EDGES
        if (e.target == "dlacli.cli" or e.target.startswith("dlacli.cli.")) and not e.importer.startswith("dlacli.cli")
    ]
    assert not bad, "only dlacli.cli may import dlacli.cli:\n" + "\n".join(bad)


@pytest.mark.parametrize("package", sorted(HEAVY))
def test_each_heavy_dependency_has_one_lazy_importer(package):
    edges = [e for e in EDGES if e.target == package or e.target.startswith(package + ".")]
    importers = {e.importer for e in edges}
    assert importers == HEAVY[package], (
        f"{package} is imported by {sorted(importers) or 'no module'}; "
        f"expected {sorted(HEAVY[package]) or 'no module under src'}:\n" + "\n".join(e.where() for e in edges)
    )
    eager = [e.where() for e in edges if not e.lazy]
    assert not eager, f"{package} must be imported inside functions (it is optional or slow):\n" + "\n".join(eager)


# --------------------------------------------------------------------------------------------
# start-up: what `dla` loads

_PROBE = """
import sys
from dlacli.cli.app import main
try:
    main(sys.argv[1:])
except SystemExit as exit:
    code = exit.code
else:
    code = 0
print(f"exit={code} torch={'torch' in sys.modules}", file=sys.stderr)
"""

_COMMANDS = {
    "version": ["--version"],
    "info-body": ["info", str(EXAMPLES / "body.json")],
    "info-motion": ["info", str(EXAMPLES / "motion.npz")],
    "info-avatar": ["info", str(EXAMPLES / "avatar.npz")],
    "info-ply": ["info", str(EXAMPLES / "gaussians_sh3.ply")],
    "info-views": ["info", str(EXAMPLES / "views")],
}


@pytest.mark.parametrize("argv", list(_COMMANDS.values()), ids=list(_COMMANDS))
def test_version_and_info_do_not_import_torch(argv):
    done = subprocess.run([sys.executable, "-c", _PROBE, *argv], capture_output=True, text=True, timeout=120)
    status = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else ""
    assert status.startswith("exit=0 "), (argv, done.stderr[-2000:])
    assert status.endswith("torch=False"), f"dla {' '.join(argv)} imported torch"
    assert done.stdout.strip(), (argv, done.stdout)


def _import_circles() -> list[list[str]]:
    """The strongly connected components of more than one module in the graph of every import
    between dlacli's modules (lazy ones included: a function-level import that closes a circle
    is still a circle in the design), found with Tarjan's algorithm."""
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for e in EDGES:
        if e.target in MODULES and e.target != e.importer:
            graph[e.importer].add(e.target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return circles


def test_the_circle_finder_finds_a_circle():
    """The oracle for the test below: a hand-made graph with one circle of three modules."""
    saved = list(EDGES)
    try:
        a, b, c = sorted(MODULES)[:3]
        EDGES.extend([Edge(a, b, 1, True), Edge(b, c, 1, True), Edge(c, a, 1, True)])
        assert any({a, b, c} <= set(circle) for circle in _import_circles())
    finally:
        EDGES[:] = saved


def test_no_import_circles():
    circles = _import_circles()
    assert not circles, "modules that import each other (directly or around a circle):\n" + "\n".join(
        " <-> ".join(c) for c in circles
    )


def test_numba_kernels_live_in_kernel_modules():
    """docs/architecture.md, "numba kernels and their torch twins": a module that compiles a numba
    kernel is named *_kernels.py, so that a kernel is found by its file's name."""
    compiling = []
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for dec in node.decorator_list:
                    target = dec.func if isinstance(dec, ast.Call) else dec
                    name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
                    if name in ("njit", "jit", "vectorize", "guvectorize", "stencil"):
                        compiling.append(path)
    assert compiling, "the scan found no kernel at all"
    assert {p.name for p in compiling if not p.name.endswith("_kernels.py")} == set()


def test_no_module_imports_another_ones_private_names():
    """What two modules share is public in the lower one: no `from dlacli.x import _name` in src."""
    private = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dlacli"):
                private += [
                    f"{path.relative_to(SRC)}: {node.module}.{a.name}"
                    for a in node.names
                    if a.name.startswith("_") and not a.name.startswith("__")
                ]
    assert private == []


def _calls(name: str) -> list[str]:
    """The modules under src that call a function called `name` (by any import path), with the line."""
    found = []
    for module, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call):
                f = node.func
                if (f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)) == name:
                    found.append(f"{module} line {node.lineno}")
    return found


def test_one_route_from_an_avatar_to_pixels():
    """docs/architecture.md: the renderer is called only by render/ and the avatar's pipeline
    (avatar/posed.py), and no stage or training turns cameras into eyes itself."""
    renders = _calls("render_gaussians")
    assert renders, "the scan found no caller at all"
    assert [c for c in renders if not c.startswith(("dlacli.render.", "dlacli.avatar."))] == []
    eyes = _calls("camera_centers")
    assert [c for c in eyes if c.startswith(("dlacli.stages.", "dlacli.train."))] == []
