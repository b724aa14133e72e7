"""The layers of docs/architecture.md hold: no package imports a higher layer, no import cycle, no private name
imported from another module. Reads the source (every import, lazy and TYPE_CHECKING ones included)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "degusta_learn"

LAYERS = {
    "errors": 0, "names": 0, "textsafe": 0, "devices": 0, "__init__": 0,
    "files": 1, "config": 1, "optim": 1, "shipped": 1, "webio": 1,
    "scene": 2, "metrics": 2,
    "render": 3,
    "task": 4,
    "methods": 5, "training": 5, "dryrun": 5,
    "synth": 6, "baselines": 6, "vlm": 6,
    "prompting": 7,
    "evaluate": 8,
    "finetune": 9,
    "pretrain": 10,
    "quickstart": 11, "planner": 11, "collect": 11, "cli": 11,
}


def _modules() -> dict[str, Path]:
    found = {}
    for path in PACKAGE.rglob("*.py"):
        parts = ("degusta_learn", *path.relative_to(PACKAGE).with_suffix("").parts)
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        found[name] = path
    return found


MODULES = _modules()


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _imports(module: str, path: Path):
    """(line, imported module, imported name or None) of every degusta_learn import in `path`."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("degusta_learn"):
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                if full in MODULES:
                    yield node.lineno, full, None
                else:
                    yield node.lineno, node.module, alias.name
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("degusta_learn"):
                    yield node.lineno, alias.name, None


def test_every_package_has_a_layer():
    assert {_unit(m) for m in MODULES} <= set(LAYERS), sorted({_unit(m) for m in MODULES} - set(LAYERS))
    documented = (PACKAGE.parent / "docs" / "architecture.md").read_text(encoding="utf-8")
    for unit in LAYERS:
        if unit != "__init__":
            assert f"`{unit}`" in documented, f"docs/architecture.md does not place {unit}"


def _shown(path: Path) -> str:
    return str(path.relative_to(PACKAGE.parent)) if path.is_relative_to(PACKAGE.parent) else str(path)


def test_no_package_imports_a_higher_layer():
    upward = []
    for module, path in MODULES.items():
        for line, target, _ in _imports(module, path):
            if LAYERS[_unit(target)] > LAYERS[_unit(module)]:
                upward.append(f"{_shown(path)}:{line}: {_unit(module)} "
                              f"(layer {LAYERS[_unit(module)]}) imports {target} (layer {LAYERS[_unit(target)]})")
    assert not upward, "\n".join(upward)


def test_no_private_name_is_imported_from_another_module():
    private = [f"{_shown(path)}:{line}: {target}.{name}"
               for module, path in MODULES.items() for line, target, name in _imports(module, path)
               if name and name.startswith("_") and not name.startswith("__")]
    assert not private, "\n".join(private)


def test_no_import_cycles_between_modules():
    graph = {m: {t for _, t, _ in _imports(m, p) if t != m and t in MODULES} for m, p in MODULES.items()}
    # a package's __init__ re-exporting its own submodules is not a cycle of the design
    for m in graph:
        graph[m] = {t for t in graph[m] if not (MODULES[m].name == "__init__.py" and t.startswith(m + "."))}
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                cycles.append(stack[stack.index(t):] + [t])
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


@pytest.mark.parametrize("line, expected", [
    ("from degusta_learn.cli import main", "imports degusta_learn.cli"),
])
def test_the_layer_check_can_fail(tmp_path, monkeypatch, line, expected):
    """A lower layer importing a higher one is caught (the check is not vacuous)."""
    fake = tmp_path / "fake.py"
    fake.write_text(line + "\n")
    module = "degusta_learn.scene.fake"
    monkeypatch.setitem(MODULES, module, fake)
    with pytest.raises(AssertionError, match=expected):
        test_no_package_imports_a_higher_layer()
