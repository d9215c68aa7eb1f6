"""Every third-party package the code imports is declared in pyproject.toml: the library and the command line
(``pipeline/``, ``flows/``) by the project's dependencies, the tests and benchmarks by those plus the ``test``
extra. A package that only arrives as another's dependency (httpx through Prefect, click through typer) can
disappear with that package's next release, so it is declared where it is imported. Imports are read with
``ast`` from every file, at any depth (imports inside functions included)."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from importlib.metadata import PackageNotFoundError, packages_distributions, requires
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FIRST_PARTY = {"pipeline", "flows", "tests", "benchmarks"}


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirement(spec: str) -> tuple[str, set[str]]:
    """(canonical distribution name, extras) of a requirement string such as ``dask[distributed]>=2024.1``."""
    m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(?:\[([^\]]*)\])?", spec)
    assert m, spec
    return _canonical(m.group(1)), {e.strip() for e in (m.group(2) or "").split(",") if e.strip()}


def _declared(specs: list[str]) -> set[str]:
    """The distributions the requirements name, with those their extras bring (``dask[distributed]`` declares
    ``distributed`` too, as the extra's metadata says)."""
    out = set()
    for spec in specs:
        name, extras = _requirement(spec)
        out.add(name)
        if not extras:
            continue
        try:
            reqs = requires(name) or []
        except PackageNotFoundError:
            continue
        for r in reqs:
            marker = re.search(r"""extra\s*==\s*["']([^"']+)["']""", r)
            if marker and marker.group(1) in extras:
                out.add(_requirement(r)[0])
    return out


def _local_modules(root: Path) -> set[str]:
    """Modules a folder's scripts import from each other by path (``benchmarks/cats_tag.py`` as ``cats_tag``)."""
    return {p.stem for p in root.glob("*.py")}


def _third_party_imports(root: Path) -> dict[str, list[str]]:
    """Top-level names of the non-standard-library, non-project modules imported under ``root`` -> the files."""
    local = FIRST_PARTY | _local_modules(REPO / "benchmarks")
    found: dict[str, list[str]] = {}
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top in sys.stdlib_module_names or top in local or top == "__future__":
                    continue
                found.setdefault(top, []).append(str(path.relative_to(REPO)))
    return found


@pytest.fixture(scope="module")
def project() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


@pytest.mark.parametrize(
    "folders, extras",
    [(("pipeline", "flows"), ()), (("tests", "benchmarks"), ("test",))],
    ids=["package", "tests-and-benchmarks"],
)
def test_every_imported_package_is_declared(project, folders, extras):
    declared = _declared(project["dependencies"] + [s for e in extras for s in project["optional-dependencies"][e]])
    dists = packages_distributions()
    missing = {}
    for folder in folders:
        for module, files in _third_party_imports(REPO / folder).items():
            owners = {_canonical(d) for d in dists.get(module, [])}
            assert owners, f"{module} (imported by {files[0]}) is installed by no distribution"
            if not owners & declared:
                missing[module] = (sorted(owners), files[0])
    assert not missing, f"imported but not declared in pyproject.toml: {missing}"


def test_the_checker_sees_what_it_must():
    """The walk finds imports inside functions and maps import names to distributions (google -> protobuf)."""
    found = _third_party_imports(REPO / "pipeline")
    assert {"numpy", "polars", "google", "scipy"} <= set(found)
    assert "protobuf" in {_canonical(d) for d in packages_distributions()["google"]}
    assert "threadpoolctl" in found  # imported inside a function only (pipeline/diagnose/diagnosis.py)
    assert _declared(["dask[distributed]>=2024.1"]) >= {"dask", "distributed"}
    assert _requirement("mcap-protobuf-support>=0.5") == ("mcap-protobuf-support", set())


def test_the_wheel_lists_every_package_and_maps_the_schemas():
    """pyproject.toml lists the packages (so that the top-level schemas/ can be the data package
    pipeline.io.schemas): the list holds every package of the tree and the two data packages (the schemas, the
    simulator's published tables), and the mapping points at the one schemas folder."""
    setup = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    tree = {
        ".".join(p.parent.relative_to(REPO).parts)
        for root in ("pipeline", "flows")
        for p in (REPO / root).rglob("__init__.py")
    }
    assert set(setup["packages"]) == tree | {"pipeline.io.schemas", "pipeline.simulate.data"}
    assert setup["package-dir"] == {"pipeline.io.schemas": "schemas"}
    assert not (REPO / "pipeline" / "io" / "schemas").exists()  # no second copy
    from pipeline.io.codecs import SCHEMA_DIR

    assert SCHEMA_DIR == REPO / "schemas"
