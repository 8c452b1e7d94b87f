"""The code's shape, checked from the source (AST): no import cycles in nbvh_core (function-local imports count
too), the layering (nbvh_core never imports bpy, the add-on never imports torch, the core modules the add-on loads
are torch-free all the way down), no function in nbvh_core over 80 lines, and every C signature declared once."""
from __future__ import annotations

import ast

import pytest
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
CORE = ROOT / "nbvh_core"
MAX_FUNCTION_LINES = 80
#: One concern per file: a module past this many lines holds more than one (the house's rule).
MAX_MODULE_LINES = 450
#: Functions allowed past MAX_FUNCTION_LINES, with the reason (none today; an entry needs one).
LONG_FUNCTIONS: dict[str, str] = {}
#: The core modules the add-on imports inside Blender's process (addon/job.py), which has no torch.
TORCH_FREE = ("nbvh_core.protocol.events", "nbvh_core.protocol.outputs", "nbvh_core.protocol.quality_levels",
              "nbvh_core.protocol.process", "nbvh_core.geometry.look", "nbvh_core.protocol.glb_reader")
#: nbvh_core's layers, lowest first, in the order data flows: a module imports from its own layer or below only
#: (function-local imports included). The package's __init__ and __main__ are entry points above them all. The
#: decision rules are pure (measurements in, typed records out), so every stage that decides can use them.
LAYERS = ("protocol", "decision", "kernels", "geometry", "neural", "storage", "training", "rendering", "planning",
          "app")
ENTRY_POINTS = ("nbvh_core", "nbvh_core.__main__")


def _module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, root: Path = ROOT) -> set[str]:
    """Every module `path` imports anywhere (top level or inside functions), as absolute dotted names; a
    `from pkg import name` counts as pkg.name when that is a module, else as pkg."""
    mod = _module_name(path, root)
    package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            out.add(target)
            out.update(f"{target}.{a.name}" for a in node.names)
    return out


def _core_graph(root: Path = ROOT) -> dict[str, set[str]]:
    files = {_module_name(p, root): p for p in (root / "nbvh_core").rglob("*.py")}
    return {m: {d for d in _imports(p, root) if d in files and d != m} for m, p in files.items()}


def _layer(module: str) -> int | None:
    parts = module.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else None


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """'module -> dependency' for every import of a higher layer (and every module in no layer)."""
    out = []
    for m, deps in sorted(graph.items()):
        if m in ENTRY_POINTS:
            continue
        if _layer(m) is None:
            out.append(f"{m} is in no layer of {LAYERS}")
            continue
        out += [f"{m} -> {d}" for d in sorted(deps) if _layer(d) is not None and _layer(d) > _layer(m)]
    return out


def test_nbvh_core_layers_import_downward_only():
    assert not layer_violations(_core_graph())


def test_a_planted_upward_import_fails_the_layer_rule(tmp_path):
    import shutil

    shutil.copytree(CORE, tmp_path / "nbvh_core", ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    mesh = tmp_path / "nbvh_core" / "geometry" / "mesh.py"
    mesh.write_text(mesh.read_text() + "\n\ndef _planted():\n    from ..app import pipeline  # noqa\n")
    assert layer_violations(_core_graph(tmp_path)) == ["nbvh_core.geometry.mesh -> nbvh_core.app",
                                                       "nbvh_core.geometry.mesh -> nbvh_core.app.pipeline"]


def test_the_addon_imports_only_the_protocol_layer():
    for p in list((ROOT / "addon").rglob("*.py")) + [ROOT / "compress.py"]:
        for i in _imports(p):
            core = i[i.index("nbvh_core"):] if "nbvh_core" in i.split(".") else None
            assert core is None or core in ("nbvh_core", "nbvh_core.protocol") or \
                core.startswith("nbvh_core.protocol."), f"{p.name} imports {i}"


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                return stack[stack.index(d):] + [d]
            if d not in state and (found := visit(d)):
                return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_no_import_cycles_in_nbvh_core():
    graph = _core_graph()
    assert len(graph) > 25  # the walk found the package
    cycle = _find_cycle(graph)
    assert cycle is None, " -> ".join(cycle)


def test_the_cycle_finder_finds_a_cycle():
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b"}, "b": set()}) is None


def test_layers_nbvh_core_has_no_bpy_and_the_addon_no_torch():
    for p in CORE.rglob("*.py"):
        assert not any(i.split(".")[0] == "bpy" for i in _imports(p)), p
    for p in list((ROOT / "addon").rglob("*.py")) + [ROOT / "compress.py"]:
        assert not any(i.split(".")[0] == "torch" for i in _imports(p)), p


def test_core_modules_the_addon_loads_are_torch_free_all_the_way_down():
    graph = _core_graph()
    files = {_module_name(p): p for p in CORE.rglob("*.py")}
    for start in TORCH_FREE:
        parents = [".".join(start.split(".")[:k]) for k in range(1, start.count(".") + 1)]
        seen, todo = set(), [start, *parents]  # importing a submodule runs its packages' __init__ first
        while todo:
            m = todo.pop()
            if m in seen:
                continue
            seen.add(m)
            assert not any(i.split(".")[0] in ("torch", "bpy") for i in _imports(files[m])), f"{start} -> {m}"
            todo.extend(graph[m])


def _repository_sources() -> list[Path]:
    """Every Python file of the repository (core, add-on, benchmarks, tests, scripts), not the environment's."""
    skip = {".venv", "build", "dist", ".git", "__pycache__"}
    return [p for p in ROOT.rglob("*.py") if not skip & set(p.relative_to(ROOT).parts)]


def test_no_function_in_the_repository_is_longer_than_80_lines():
    long = []
    for p in _repository_sources():
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                name = f"{_module_name(p)}.{node.name}"
                if n > MAX_FUNCTION_LINES and name not in LONG_FUNCTIONS:
                    long.append(f"{name}: {n} lines")
    assert not long, long


def _calls_the_library(tree: ast.AST) -> list[str]:
    """What in a module reaches the compiled library directly: a `nbvh_*` attribute (a C entry), a raw address
    (`data_ptr`, `.ctypes.data`) or the library handle (`load()` of kernels)."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and (node.attr.startswith("nbvh_") or node.attr == "data_ptr"
                                                or node.attr == "data" and isinstance(node.value, ast.Attribute)
                                                and node.value.attr == "ctypes"):
            found.append(f"line {node.lineno}: .{node.attr}")
        if isinstance(node, ast.ImportFrom) and (node.module or "").endswith("kernels.library"):
            found.append(f"line {node.lineno}: imports kernels.library")
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "load"
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "kernels"):
            found.append(f"line {node.lineno}: kernels.load()")
    return found


def test_no_module_in_nbvh_core_is_longer_than_450_lines():
    long = {str(p.relative_to(ROOT)): n for p in sorted(CORE.rglob("*.py"))
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, long


def test_only_the_bindings_module_calls_the_compiled_library():
    allowed = {"nbvh_core.kernels.bindings", "nbvh_core.kernels.library", "nbvh_core.kernels"}
    offenders = {}
    for p in sorted(CORE.rglob("*.py")):
        name = _module_name(p)
        if name not in allowed and (found := _calls_the_library(ast.parse(p.read_text()))):
            offenders[name] = found
    assert not offenders, offenders
    planted = "from ..kernels import load\nx = load().nbvh_encode_forward(t.data_ptr())\n"
    assert len(_calls_the_library(ast.parse(planted))) == 2



def test_every_message_that_crosses_a_process_is_declared_in_the_protocol():
    """The wire contract: each event ("event": KIND) and render-worker request ("op": KIND) written anywhere in
    nbvh_core or the add-on is declared in nbvh_core/protocol/events.py; a planted undeclared one is caught."""
    import re

    from nbvh_core.protocol.events import EVENTS, WORKER_REQUESTS, event

    def undeclared(texts: dict[str, str]) -> list[str]:
        out = []
        for name, text in texts.items():
            out += [f"{name}: event {k}" for k in re.findall(r"""["']event["']\s*:\s*["'](\w+)["']""", text)
                    if k not in EVENTS]
            out += [f"{name}: op {k}" for k in re.findall(r"""["']op["']\s*:\s*["'](\w+)["']""", text)
                    if k not in WORKER_REQUESTS]
        return out

    files = {str(p.relative_to(ROOT)): p.read_text() for d in ("nbvh_core", "addon") for p in (ROOT / d).rglob("*.py")}
    assert not undeclared(files)
    assert undeclared({"planted.py": 'sink({"event": "teleported", "x": 1})'}) == ["planted.py: event teleported"]
    assert event("warning", message="m") == {"event": "warning", "message": "m"}
    with pytest.raises(ValueError, match="undeclared event"):
        event("teleported")


def test_every_message_is_built_by_its_one_constructor():
    """Each declared event and request has exactly one constructor in the protocol, which builds its kind; no code
    outside the protocol writes a message as a dict literal (a planted one is caught)."""
    import ast

    from nbvh_core.protocol import events as wire

    assert set(wire.CONSTRUCTORS) == set(wire.EVENTS) and set(wire.REQUEST_CONSTRUCTORS) == set(wire.WORKER_REQUESTS)
    assert len(set(wire.CONSTRUCTORS.values())) == len(wire.CONSTRUCTORS)
    samples = {"phase": dict(phase="p", message="m"), "progress": dict(fraction=0.5), "warning": dict(message="m"),
               "verdict": dict(message="m", assessment=None), "written": dict(files=[]), "asset": dict(phase="train"),
               "result": {}, "error": dict(message="m"), "ready": dict(pid=1),
               "scene": dict(id=1, objects=0, warnings=[], seconds=0.0),
               "frame": dict(channel="c", id=1, level=1, width=2, height=2, path="p", seconds=0.0, last=True),
               "superseded": dict(channel="c", id=1), "exit": {}}
    for kind, make in wire.CONSTRUCTORS.items():
        assert make(**samples[kind])["event"] == kind
    # a field may be named like the message's own kind key ('kind' of an error or a written file)
    assert wire.error(message="m", kind="bad_input")["kind"] == "bad_input"
    assert wire.written(files=[], kind="mesh") == {"event": "written", "files": [], "kind": "mesh"}
    requests = {"scene": dict(id=1, scene={}), "render": dict(channel="c", id=1, camera=[], width=2, height=2),
                "cancel": dict(channel="c"), "quit": {}}
    for op, make in wire.REQUEST_CONSTRUCTORS.items():
        assert make(**requests[op])["op"] == op

    def literals(name: str, text: str) -> list[str]:
        return [f"{name}:{node.lineno}" for node in ast.walk(ast.parse(text))
                if isinstance(node, ast.Dict) and node.keys and isinstance(node.keys[0], ast.Constant)
                and node.keys[0].value in ("event", "op")]

    protocol = ROOT / "nbvh_core" / "protocol"
    found = [hit for d in ("nbvh_core", "addon") for p in (ROOT / d).rglob("*.py") if protocol not in p.parents
             for hit in literals(str(p.relative_to(ROOT)), p.read_text())]
    assert not found, found
    assert literals("planted.py", 'sink({"event": "phase", "phase": "x"})') == ["planted.py:1"]


def test_every_relative_import_in_the_addon_names_a_module_that_exists():
    """Imports inside functions run only when Blender calls them (a render, a timer): a stale name there passes
    every import-time check. nbvh_core is copied into the add-on's zip by build_addon.py."""
    import ast

    missing = []
    for p in (ROOT / "addon").rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                names = [node.module] if node.module else [a.name for a in node.names]
                for name in names:
                    head = name.split(".")[0]
                    if head != "nbvh_core" and not (ROOT / "addon" / f"{head}.py").exists() \
                            and not (ROOT / "addon" / head).is_dir():
                        missing.append(f"{p.name}:{node.lineno} .{name}")
    assert not missing, missing
