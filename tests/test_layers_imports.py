"""The layers of docs/architecture.md, held against every import statement in the code.

client_py <- fitter.fitting <- fitter.collection <- fitter.server <- fitter.cli/demo: a
module imports only its own layer and those below it. Read from the source with ``ast``
(imports inside functions count too), so a lazy import cannot hide a wrong arrow.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LAYERS = ["client_py", "fitter.fitting", "fitter.collection", "fitter.server", "fitter.cli"]
#: what the serving process may take from the fitting library: the option table alone
SERVER_FROM_FITTING = {"fitter.fitting.options"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[tuple[str, bool]]:
    """``(absolute module, at module level)`` for each import in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    top = {id(node) for node in tree.body}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, id(node) in top) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            if node.level and not node.module:  # from . import a, b
                found += [(f"{name}.{alias.name}", id(node) in top) for alias in node.names]
            else:
                found.append((name, id(node) in top))
    return found


def _layer(module: str) -> int | None:
    for index in range(len(LAYERS) - 1, -1, -1):
        if module == LAYERS[index] or module.startswith(LAYERS[index] + "."):
            return index
    if module in ("fitter.demo",):
        return len(LAYERS) - 1
    return None


def _sources() -> list[Path]:
    return sorted(p for folder in ("client_py", "fitter") for p in (ROOT / folder).rglob("*.py"))


@pytest.mark.parametrize("path", _sources(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_imports_point_down(path):
    own = _layer(_module_name(path))
    wrong = [name for name, _ in _imports(path)
             if (_layer(name) or -1) > (own if own is not None else len(LAYERS))]
    assert wrong == []


@pytest.mark.parametrize("path", sorted((ROOT / "fitter" / "server").rglob("*.py")),
                         ids=lambda p: p.relative_to(ROOT).as_posix())
def test_the_server_takes_only_the_option_table_from_the_fit(path):
    taken = {name for name, _ in _imports(path) if name.startswith("fitter.fitting")}
    assert taken <= SERVER_FROM_FITTING


@pytest.mark.parametrize("path", sorted((ROOT / "fitter" / "collection").rglob("*.py")),
                         ids=lambda p: p.relative_to(ROOT).as_posix())
def test_the_collection_has_no_flask(path):
    assert [n for n, _ in _imports(path) if n.split(".")[0] in ("flask", "werkzeug")
            and not n.startswith("werkzeug.security")] == []


@pytest.mark.parametrize("path", sorted((ROOT / "client_py").rglob("*.py")),
                         ids=lambda p: p.relative_to(ROOT).as_posix())
def test_client_py_imports_the_standard_library_at_module_level(path):
    allowed = set(sys.stdlib_module_names) | {"client_py", "__future__"}
    if path.name.startswith(("_kernel_numpy", "_numpy_basis")):  # imported only with numpy
        allowed.add("numpy")
    outside = [n for n, top in _imports(path) if top and n.split(".")[0] not in allowed]
    assert outside == []
