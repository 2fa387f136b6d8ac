"""The package's layering, read from the source: every import of a pivla module (at module level or inside a
function) goes to the same layer or one below, and no set of modules imports itself in a circle."""

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

# bottom -> top; a module belongs to the longest prefix listed
LAYERS = [
    ("pivla.io", "pivla.config"),
    ("pivla.arm",),
    ("pivla.model",),
    ("pivla.data",),
    ("pivla.training",),
    ("pivla.envs",),
    ("pivla.control",),
    ("pivla.policy",),
    ("pivla.robot",),
    ("pivla.serving",),
    ("pivla.evaluation",),
    ("pivla.experiments",),
    ("pivla.bench",),
    ("pivla.cli", "pivla.__main__"),
]


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _layer(module: str) -> int | None:
    best, found = -1, None
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best:
                best, found = len(p), i
    return found


def _imports() -> dict[str, set[str]]:
    """module -> pivla modules it imports anywhere in its source (``from pivla.x import y`` counts as
    pivla.x.y when that is a module, else pivla.x)."""
    files = {_module_name(p): p for p in (SRC / "pivla").rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        deps = set()
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                deps |= {a.name for a in node.names if a.name.startswith("pivla")}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1]
                                    + ([base] if base else []))
                if not base.startswith("pivla"):
                    continue
                for a in node.names:
                    deps.add(f"{base}.{a.name}" if f"{base}.{a.name}" in files else base)
        graph[name] = {d for d in deps if d in files and d != name}
    return graph


def test_every_module_has_a_layer():
    missing = sorted(m for m in _imports() if m != "pivla" and _layer(m) is None)
    assert not missing, f"modules outside every layer: {missing}"


def test_imports_never_go_up_a_layer():
    """The package root is a facade (``pivla.load_policy``): it may name anything, and only ``__version__``
    may be imported from it."""
    up = []
    for module, deps in _imports().items():
        if module == "pivla":
            continue
        for dep in deps:
            if dep == "pivla":
                continue
            if _layer(dep) > _layer(module):
                up.append(f"{module} -> {dep}")
    assert not up, "imports that go up a layer:\n" + "\n".join(sorted(up))


def test_only_the_version_is_imported_from_the_package_root():
    bad = []
    for path in (SRC / "pivla").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module == "pivla" and not node.level:
                names = {a.name for a in node.names if not (SRC / "pivla" / f"{a.name}.py").exists()
                         and not (SRC / "pivla" / a.name).is_dir()} - {"__version__"}
                if names:
                    bad.append(f"{path.relative_to(SRC)}: {sorted(names)}")
    assert not bad, bad


def test_no_import_circles():
    graph = _imports()
    index, low, stack, on_stack, circles = {}, {}, [], set(), []
    counter = [0]

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
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

    for v in list(graph):
        if v not in index:
            visit(v)
    assert not circles, f"import circles: {circles}"


@pytest.mark.parametrize("module", ["pivla.control", "pivla.control.executors", "pivla.serving.client",
                                    "pivla.data.transforms", "pivla.arm"])
def test_the_robot_side_imports_no_torch(module):
    """What a robot laptop runs (executors, the remote policy, picture preparation, the arm's kinematics) imports
    neither torch nor MuJoCo."""
    import subprocess
    import sys

    code = (f"import sys, {module}; bad = [m for m in ('torch', 'mujoco') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
