"""The package layout (issue 12): no import circles anywhere in ``pipeline`` or ``flows`` (any import, at any depth
of a file, counts), ``pipeline`` never imports Prefect, and the package docstring names every sub-package."""

from __future__ import annotations

import ast
from pathlib import Path

import pipeline

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "flows")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))}


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The project modules ``name`` imports, anywhere in the file (functions included); ``from a import b`` counts
    as importing ``a.b`` where that is a module, else ``a``."""
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                anchor = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                mod = ".".join([*anchor, mod] if mod else anchor)
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in known else mod for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in known:  # import a.b.c of a module a.b: the module imported is a.b
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    return {name: _imports(name, path, set(mods)) for name, path in mods.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m) :] + [m]
            if m not in state and (found := visit(m)):
                return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (found := visit(n)):
            return found
    return None


def test_no_import_circles():
    graph = _graph()
    assert len(graph) > 30
    assert _cycle(graph) is None, " -> ".join(_cycle(graph))


def test_cycle_finder_finds_a_circle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_pipeline_never_imports_prefect():
    for path in (REPO / "pipeline").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            assert not any(n.split(".")[0] in ("prefect", "prefect_dask", "flows") for n in names), path


def test_docstring_and_readme_name_every_subpackage():
    subpackages = sorted(p.parent.name for p in (REPO / "pipeline").glob("*/__init__.py"))
    assert {"io", "simulate", "calibrate", "passport", "diagnose"} <= set(subpackages)
    readme = (REPO / "README.md").read_text()
    for sub in subpackages:
        assert f"``{sub}``" in pipeline.__doc__, sub
        assert f"pipeline/{sub}/" in readme, sub


def test_shared_constants_have_one_home():
    """Nanoseconds per second and the slab size are defined once (pipeline.run), not per module."""
    homes: dict[str, list[str]] = {"1_000_000_000": [], "1 << 20": []}
    for path in sorted((REPO / "pipeline").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Assign):
                continue
            v = node.value
            if isinstance(v, ast.Constant) and v.value == 1_000_000_000:
                homes["1_000_000_000"].append(str(path.relative_to(REPO)))
            elif (
                isinstance(v, ast.BinOp)
                and isinstance(v.op, ast.LShift)
                and isinstance(v.left, ast.Constant)
                and isinstance(v.right, ast.Constant)
                and (v.left.value, v.right.value) == (1, 20)
            ):
                homes["1 << 20"].append(str(path.relative_to(REPO)))
    assert homes == {"1_000_000_000": ["pipeline/run.py"], "1 << 20": ["pipeline/run.py"]}, homes


#: (a layer, the layers above it that it may not import, at any depth of a file): the passport layer reads what the
#: methods and diagnose wrote, through models that live below them (the extended model in pipeline.effects.model,
#: the thermosensor and the ramp direction in pipeline.dynamics); apply uses the passport, not its makers
LOWER_LAYERS = {
    "pipeline.passport": ("pipeline.diagnose", "pipeline.calibrate", "pipeline.apply", "pipeline.inspect"),
    "pipeline.apply": ("pipeline.diagnose", "pipeline.calibrate", "pipeline.inspect"),
    "pipeline.calibrate": ("pipeline.diagnose", "pipeline.inspect", "pipeline.apply"),
    "pipeline.effects": ("pipeline.diagnose", "pipeline.calibrate", "pipeline.passport", "pipeline.apply"),
    "pipeline.dynamics": ("pipeline.diagnose", "pipeline.calibrate", "pipeline.passport", "pipeline.effects"),
    "pipeline.thermal": ("pipeline.diagnose", "pipeline.calibrate", "pipeline.passport", "pipeline.effects"),
    "pipeline.model": ("pipeline.diagnose", "pipeline.calibrate", "pipeline.passport", "pipeline.effects"),
}


def _in(module: str, layer: str) -> bool:
    return module == layer or module.startswith(layer + ".")


def _back_arrows(graph: dict[str, set[str]]) -> list[str]:
    return sorted(
        f"{a} -> {b}"
        for a, imported in graph.items()
        for layer, above in LOWER_LAYERS.items()
        if _in(a, layer)
        for b in imported
        if any(_in(b, up) for up in above)
    )


def test_no_arrow_runs_back_up():
    assert _back_arrows(_graph()) == []


def test_back_arrow_finder_finds_one():
    assert _back_arrows({"pipeline.passport.document": {"pipeline.diagnose.model", "pipeline.thermal"}}) == [
        "pipeline.passport.document -> pipeline.diagnose.model"
    ]


def test_no_private_api_of_python_or_other_packages():
    """Supported APIs only (issue 27): ``pipeline`` and ``flows`` use no private name (``_x``) of the standard
    library or another package (``threading._shutdown``, ``typer._click``, ``prefect._internal``, ...), neither
    through an attribute nor in an import. ``os._exit`` is a documented function."""
    allowed = {"os._exit"}
    found = []
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            tree = ast.parse(path.read_text())
            modules = {"os", "sys", "threading", "atexit", "signal", "socket", "multiprocessing"}
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    modules |= {(a.asname or a.name).split(".")[0] for a in node.names}
                    for a in node.names:
                        if any(n.startswith("_") and not n.startswith("__") for n in a.name.split(".")):
                            found.append(f"{path.relative_to(REPO)}:{node.lineno} import {a.name}")
                elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                    if node.module.split(".")[0] in PACKAGES:
                        continue
                    names = [*node.module.split("."), *(a.name for a in node.names)]
                    if any(n.startswith("_") and not n.startswith("__") for n in names):
                        found.append(f"{path.relative_to(REPO)}:{node.lineno} from {node.module} import ...")
                    modules |= {a.asname or a.name for a in node.names}  # (a module or an object of one)
            modules -= set(PACKAGES)
            for node in ast.walk(tree):
                if (  # getattr(threading, "_shutdown"), hasattr(core.X, "_y"), setattr(...)
                    isinstance(node, ast.Call)
                    and isinstance(node.func, ast.Name)
                    and node.func.id in ("getattr", "hasattr", "setattr")
                    and len(node.args) >= 2
                    and isinstance(node.args[1], ast.Constant)
                    and str(node.args[1].value).startswith("_")
                    and not str(node.args[1].value).startswith("__")
                    and isinstance(root := node.args[0], ast.Attribute | ast.Name)
                ):
                    while isinstance(root, ast.Attribute):
                        root = root.value
                    if isinstance(root, ast.Name) and root.id in modules:
                        found.append(
                            f"{path.relative_to(REPO)}:{node.lineno} {node.func.id}(..., {node.args[1].value!r})"
                        )
                if not isinstance(node, ast.Attribute):
                    continue
                chain, base = [node.attr], node.value
                while isinstance(base, ast.Attribute):
                    chain.insert(0, base.attr)
                    base = base.value
                if not (isinstance(base, ast.Name) and base.id in modules):
                    continue
                dotted = ".".join([base.id, *chain])
                private = any(c.startswith("_") and not c.startswith("__") for c in chain)
                if private and dotted not in allowed:
                    found.append(f"{path.relative_to(REPO)}:{node.lineno} {dotted}")
    assert not found, found
