"""The package surface: exports, the stub of the extension, documented examples, and
the shape of the package (a one-way chain of imports, no private names shared)."""

from __future__ import annotations

import ast
import doctest
import importlib
import importlib.util
import inspect
from dataclasses import dataclass
from pathlib import Path

import pytest

import vesselflow
import vesselflow.skeletonizer


def test_public_names():
    assert set(vesselflow.__all__) == {
        "Skeletonizer",
        "VesselGraph",
        "VolumeError",
        "__version__",
        "load_graph",
        "load_volume",
        "skeletonize",
    }
    assert vesselflow.__version__.count(".") == 2


DOCUMENTED = ["vesselflow.skeletonizer", "vesselflow.graph", "vesselflow.analysis"]
DOCUMENTED += ["vesselflow.metrics", "vesselflow.compare"]


def public_api() -> dict[str, object]:
    """The public functions, classes and methods of the documented modules and of the
    package's ``__all__``, by dotted name."""
    api: dict[str, object] = {}
    spaces = [(m, importlib.import_module(m)) for m in DOCUMENTED]
    for module_name, module in [*spaces, ("vesselflow", vesselflow)]:
        names = getattr(module, "__all__", None) or vars(module)
        for name in names:
            obj = getattr(module, name)
            mine = getattr(obj, "__module__", None) == module_name or module_name == "vesselflow"
            if name.startswith("_") or not mine:
                continue
            if inspect.isfunction(obj):
                api[f"{module_name}.{name}"] = obj
            elif inspect.isclass(obj):
                api[f"{module_name}.{name}"] = obj
                for member, value in vars(obj).items():
                    if inspect.isfunction(value) and not member.startswith("_"):
                        api[f"{module_name}.{name}.{member}"] = value
    return api


@pytest.mark.parametrize("name", sorted(public_api()))
def test_every_public_function_has_returns_and_an_example(name):
    obj = public_api()[name]
    doc = inspect.getdoc(obj) or ""
    if inspect.isclass(obj) and issubclass(obj, Exception):
        assert doc, f"{name} has no docstring"
        return
    assert "\nExamples\n--------\n" in doc, f"{name} has no Examples section"
    assert ">>> " in doc.split("\nExamples\n--------\n")[-1], f"{name}: an empty example"
    returned = inspect.signature(obj).return_annotation if inspect.isfunction(obj) else "None"
    if returned not in ("None", None):
        assert "\nReturns\n-------\n" in doc, f"{name} has no Returns section"


@pytest.mark.parametrize("module", DOCUMENTED)
def test_docstring_examples_run(module):
    result = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0
    assert result.failed == 0


def test_volume_error_is_public_and_a_value_error(tmp_path):
    assert vesselflow.VolumeError.__module__.startswith("vesselflow")
    assert issubclass(vesselflow.VolumeError, ValueError)
    assert vesselflow.VolumeError.__doc__
    bad = tmp_path / "not_a_volume.npy"
    bad.write_bytes(b"not an npy file")
    with pytest.raises(vesselflow.VolumeError, match=r"not_a_volume\.npy"):
        vesselflow.load_volume(bad)


@pytest.mark.skipif(importlib.util.find_spec("mypy") is None, reason="mypy not installed")
def test_core_stub_matches_the_extension():
    from mypy import stubtest

    assert stubtest.test_stubs(stubtest.parse_options(["vesselflow._core"])) == 0


# --- the shape of the package: a one-way chain of imports, no private names shared

PACKAGE = Path(vesselflow.__file__).resolve().parent


def package_modules() -> dict[str, Path]:
    """Every module of the package, dotted name -> source file (a package by its
    ``__init__.py``); the compiled ``_core`` has no source."""
    modules = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


MODULES = package_modules()
KNOWN = {*MODULES, "vesselflow._core"}


@dataclass(frozen=True)
class Import:
    """One reference of a package module to another: ``name`` is the imported name
    (None for a whole module), ``deferred`` when the import runs inside a function."""

    importer: str
    target: str
    name: str | None
    deferred: bool
    line: int


def is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def package_imports(module: str, path: Path) -> tuple[list[Import], list[str]]:
    """The package imports of ``module`` (those under ``if TYPE_CHECKING:`` left out,
    as they never run) and its uses of private attributes of package modules
    (``io._atomic``), as ``"module:line: what"``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    imports: list[Import] = []
    aliases: dict[str, str] = {}  # local name -> package module it is bound to

    def absolute(node: ast.ImportFrom) -> str:
        if node.level == 0:
            return node.module or ""
        base = module.split(".")
        base = base if is_package else base[:-1]
        base = base[: len(base) - (node.level - 1)]
        return ".".join(base + ([node.module] if node.module else []))

    def visit(node: ast.AST, deferred: bool) -> None:
        if isinstance(node, ast.If) and is_type_checking(node.test):
            for child in node.orelse:
                visit(child, deferred)
            return
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            deferred = True
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in KNOWN:
                    imports.append(Import(module, alias.name, None, deferred, node.lineno))
                    if alias.asname:
                        aliases[alias.asname] = alias.name
        elif isinstance(node, ast.ImportFrom):
            source = absolute(node)
            for alias in node.names:
                submodule = f"{source}.{alias.name}"
                if submodule in KNOWN:
                    imports.append(Import(module, submodule, None, deferred, node.lineno))
                    aliases[alias.asname or alias.name] = submodule
                elif source in KNOWN:
                    imports.append(Import(module, source, alias.name, deferred, node.lineno))
        for child in ast.iter_child_nodes(node):
            visit(child, deferred)

    visit(tree, deferred=False)
    private_uses = [
        f"{module}:{node.lineno}: {aliases[node.value.id]}.{node.attr}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Attribute)
        and isinstance(node.value, ast.Name)
        and node.value.id in aliases
        and is_private(node.attr)
        and f"{aliases[node.value.id]}.{node.attr}" not in KNOWN
        and not shares_internals(module, aliases[node.value.id])
    ]
    return imports, private_uses


def is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


ALL = {module: package_imports(module, path) for module, path in MODULES.items()}
IMPORTS = [i for imports, _ in ALL.values() for i in imports if i.target != i.importer]


def cycle(edges: set[tuple[str, str]]) -> list[str] | None:
    """A cycle of the directed graph ``edges`` as a list of nodes, or None."""
    successors: dict[str, set[str]] = {}
    for a, b in edges:
        successors.setdefault(a, set()).add(b)
    state: dict[str, int] = {}  # 1 on the current path, 2 done
    path: list[str] = []

    def search(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(successors.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (found := search(nxt)):
                return found
        path.pop()
        state[node] = 2
        return None

    for start in sorted(successors):
        if start not in state and (found := search(start)):
            return found
    return None


def test_the_import_checker_sees_imports_cycles_and_private_names(tmp_path):
    # The checker itself, on a made-up module: else a broken checker passes everything.
    source = tmp_path / "made_up.py"
    source.write_text(
        "from typing import TYPE_CHECKING\n"
        "from vesselflow.graph import VesselGraph, _RUN_HINT\n"
        "from vesselflow import io\n"
        "if TYPE_CHECKING:\n"
        "    from vesselflow.plot import plot\n"
        "def f():\n"
        "    from vesselflow.analysis import branches\n"
        "    return io._temp_beside\n"
    )
    imports, private_uses = package_imports("vesselflow.made_up", source)
    found = {(i.target, i.name, i.deferred) for i in imports}
    assert found == {
        ("vesselflow.graph", "VesselGraph", False),
        ("vesselflow.graph", "_RUN_HINT", False),
        ("vesselflow.io", None, False),
        ("vesselflow.analysis", "branches", True),
    }
    assert private_uses == ["vesselflow.made_up:8: vesselflow.io._temp_beside"]
    assert shares_internals("vesselflow.synth.tree", "vesselflow.synth._common")
    assert shares_internals("vesselflow.io", "vesselflow._util")
    assert not shares_internals("vesselflow.metrics", "vesselflow.synth._common")
    assert not shares_internals("vesselflow.metrics", "vesselflow.analysis")
    assert cycle({("a", "b"), ("b", "c"), ("c", "a"), ("c", "d")}) == ["a", "b", "c", "a"]
    assert cycle({("a", "b"), ("b", "c"), ("a", "c")}) is None


def shares_internals(importer: str, target: str) -> bool:
    """Whether ``target`` is a private module (``_core``, ``_util``, ``synth._common``)
    of a package that ``importer`` belongs to: such a module exists to share the
    package's internals, whatever their names."""
    package, _, last = target.rpartition(".")
    return last.startswith("_") and importer.startswith(f"{package}.")


def test_no_module_imports_a_private_name_of_another():
    # What one module needs from another is made public, or moved to a private
    # module of the package; a checker's own test is above.
    private = [
        f"{i.importer}:{i.line}: {i.target}.{i.name}"
        for i in IMPORTS
        if i.name is not None and is_private(i.name) and not shares_internals(i.importer, i.target)
    ]
    private += [use for _, uses in ALL.values() for use in uses]
    assert private == []


def test_imports_form_a_one_way_chain():
    at_import = {(i.importer, i.target) for i in IMPORTS if not i.deferred}
    assert cycle(at_import) is None
    # The bottom: graph needs only the core (and the small ``_util``); the top: no
    # module of the package imports the package itself.
    assert {b for a, b in at_import if a == "vesselflow.graph"} <= {
        "vesselflow._core",
        "vesselflow._util",
    }
    assert {a for a, b in at_import if b == "vesselflow"} <= {"vesselflow.__main__"}
    # Imports inside functions run later, so they cannot break the import order, but
    # they still must not go round in circles. The one exception: VesselGraph's
    # convenience methods (save, branches, plot, ...) call the modules that implement
    # them, which all build on graph.
    everything = at_import | {
        (i.importer, i.target) for i in IMPORTS if i.importer != "vesselflow.graph"
    }
    assert cycle(everything) is None


def test_the_repository_cites_no_document_outside_it():
    # The method and its departures are in docs/method.md; a user has no ../shared.
    root = PACKAGE.parent.parent
    if not (root / "docs" / "method.md").exists():
        pytest.skip("not a source checkout")
    sources = [root / "README.md", root / "mkdocs.yml"]
    for folder, pattern in (
        ("src", "*.rs"),
        ("crates", "*.rs"),
        ("python", "*.py"),
        ("docs", "*.md"),
    ):
        sources += sorted((root / folder).rglob(pattern))
    cited = [
        f"{path.relative_to(root)}:{n}"
        for path in sources
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if "METHOD.md" in line or "shared/docs" in line
    ]
    assert cited == []


def test_the_parameter_guide_lists_every_parameter_with_its_default():
    guide = PACKAGE.parent.parent / "docs" / "parameters.md"
    if not guide.exists():
        pytest.skip("not a source checkout")
    table = guide.read_text(encoding="utf-8").split("## Every parameter", 1)[1]
    rows = [line.split("|")[1:3] for line in table.splitlines() if line.startswith("| `")]
    documented = {
        name.strip().strip("`"): default.strip().strip("`").strip('"') for name, default in rows
    }
    params = vesselflow.Skeletonizer().params
    assert list(documented) == list(params)
    for name, value in params.items():
        if isinstance(value, (bool, str)):
            assert documented[name] == str(value), name
        else:
            assert float(documented[name]) == value, name
