"""The pure core imports no I/O, clock or offline stack; the offline stack is imported lazily."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys

from tests.conftest import subprocess_env

CORE = ["motcomp.core.compensator", "motcomp.core.tuning", "motcomp.core.models",
        "motcomp.core.loop", "motcomp.core.saturation", "motcomp.core.pid", "motcomp.core.lti"]
FORBIDDEN_IN_CORE = ["scipy", "matplotlib", "zenoh", "can", "cantools", "msgpack", "pydantic",
                     "mcap", "socket", "threading", "logging"]


def loaded_after(imports: list[str], plain: bool = False) -> set[str]:
    code = (f"import sys\nfor m in {imports!r}: __import__(m)\n"
            "import json; print(json.dumps(sorted(sys.modules)))")
    env = {**subprocess_env(), **({"MOTCOMP_PURE_PYTHON": "1"} if plain else {})}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, check=True).stdout
    return {m.split(".")[0] for m in json.loads(out)}


def test_core_is_pure() -> None:
    # each module's own imports (a compiled build loads the whole tick at once, msgpack with it:
    # motcomp/core/native.py)
    mods = loaded_after(CORE, plain=True)
    assert not mods & set(FORBIDDEN_IN_CORE), mods & set(FORBIDDEN_IN_CORE)
    # the tick decodes its input frames: msgpack (a pure codec) is all it adds
    mods = loaded_after(["motcomp.core.tick"])
    assert not mods & (set(FORBIDDEN_IN_CORE) - {"msgpack"}), mods & set(FORBIDDEN_IN_CORE)


def test_design_imports_scipy_and_matplotlib_lazily() -> None:
    mods = loaded_after(["motcomp.design.frequency", "motcomp.design.timedomain",
                         "motcomp.design.report", "motcomp.cli"])
    assert "matplotlib" not in mods
    assert "scipy" not in mods


def _import_graph() -> dict[str, set[str]]:
    """motcomp's modules and the motcomp modules each imports (anywhere in it, function-level
    imports included; ``if TYPE_CHECKING:`` blocks excluded)."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    files = {".".join(p.relative_to(root).with_suffix("").parts).removesuffix(".__init__"): p
             for p in (root / "motcomp").rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for mod, path in files.items():
        tree = ast.parse(path.read_text())
        skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                and ast.unparse(node.test).endswith("TYPE_CHECKING") for n in ast.walk(node)}
        deps: set[str] = set()
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            deps |= {n for n in names if n in files and n != mod}
        graph[mod] = deps
    return graph


def test_no_import_circles() -> None:
    """No module of motcomp imports, directly or through others, a module that imports it."""
    graph = _import_graph()
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycles.append([*stack[stack.index(d):], d])
            elif d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    # a package importing its own submodules (its public surface) is not a circle
    cycles = [c for c in cycles if not any(b.startswith(a + ".") for a, b in itertools.pairwise(c))]
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


def test_layers_import_downwards() -> None:
    """The pure core imports nothing above it; config imports no runtime; design no simulator;
    replay not the service."""
    graph = _import_graph()
    up = {m: {d for d in deps if not d.startswith(("motcomp.core", "motcomp.errors"))}
          for m, deps in graph.items() if m.startswith("motcomp.core")}
    assert not any(up.values()), up
    assert not {d for d in graph["motcomp.config"] if d.startswith("motcomp.runtime")}
    for m, deps in graph.items():
        if m.startswith("motcomp.design"):
            assert not {d for d in deps if d.startswith("motcomp.sim")}, m
        if m.startswith("motcomp.replay"):
            assert "motcomp.runtime.service" not in deps, m
