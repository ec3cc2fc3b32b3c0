"""The package's layers, read from its imports: data flows one way (file format -> Scene -> rays or views -> sampler or
rasteriser -> compositing -> loss), so no module imports one of a higher layer, and no import cycle exists, counting
the imports inside functions and the package ``__init__`` files an import runs."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "nerf_lightning"

# bottom to top; a module may import its own layer's and lower ones'. The name is the first part below the package
# (a subpackage or a root module); "" is the package's own __init__.
LAYERS = [
    {"", "errors", "io", "compiling", "devices", "metrics", "config", "parameters", "conf", "lazy"},
    {"geometry", "checkpoints"},
    {"data", "fields"},
    {"rendering", "splats", "capture"},
    {"models"},
    {"training", "outputs"},
    {"viz"},
    {"bench"},
    # the commands
    {"cli"},
]


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(path): path for path in PACKAGE.rglob("*.py")}


def imported(name: str, path: Path, known: dict[str, Path], type_checking: bool = False) -> set[str]:
    """The package's modules that importing ``name`` runs: every module its import statements name (inside functions
    too; under ``if TYPE_CHECKING:`` only with ``type_checking``, for what a type checker reads), and the ``__init__``
    of every package above them."""

    def resolve(dotted: str) -> str | None:
        while dotted and dotted not in known:
            dotted = dotted.rpartition(".")[0]
        return dotted or None

    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text())
    skipped = set() if type_checking else {id(node) for block in ast.walk(tree) if isinstance(block, ast.If) and "TYPE_CHECKING" in ast.unparse(block.test)
               for statement in block.body for node in ast.walk(statement)}
    found = set()
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        elif isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        else:
            continue
        for target in targets:
            if target.split(".")[0] != "nerf_lightning" or (resolved := resolve(target)) is None:
                continue
            parts = resolved.split(".")
            found |= {".".join(parts[:k]) for k in range(2, len(parts) + 1)}  # the packages above it run first
    found.discard(name)
    return {module for module in found if not name.startswith(module + ".")}  # a package's own parents are running


def layer_of(module: str) -> int:
    part = module.split(".")[1] if "." in module else ""
    for level, names in enumerate(LAYERS):
        if part in names:
            return level
    raise AssertionError(f"{module}: its part {part!r} has no layer in tests/test_layers.py's LAYERS: give it one")


def graph(type_checking: bool = False) -> dict[str, set[str]]:
    known = modules()
    return {name: imported(name, path, known, type_checking) for name, path in known.items()}


@pytest.mark.parametrize("type_checking", [False, True], ids=["run", "type-checked"])
def test_no_module_imports_a_higher_layer(type_checking):
    upward = [f"{module} (layer {layer_of(module)}) imports {target} (layer {layer_of(target)})"
              for module, targets in graph(type_checking).items() for target in sorted(targets) if layer_of(target) > layer_of(module)]
    assert not upward, "\n".join(upward)


@pytest.mark.parametrize("type_checking", [False, True], ids=["run", "type-checked"])
def test_no_import_cycle(type_checking):
    """Neither at run time nor as a type checker reads the imports (those under ``if TYPE_CHECKING:`` too)."""
    edges = graph(type_checking)
    cycles, state = [], {}

    def visit(module: str, trail: list[str]) -> None:
        state[module] = "open"
        for target in sorted(edges[module]):
            if state.get(target) == "open":
                cycles.append(" -> ".join(trail[trail.index(target):] + [target]))
            elif target not in state:
                visit(target, trail + [target])
        state[module] = "done"

    for module in sorted(edges):
        if module not in state:
            visit(module, [module])
    assert not cycles, "\n".join(cycles)


def test_the_reader_sees_imports_inside_functions_and_the_packages_they_run(tmp_path):
    """The check itself: a lazy import inside a function counts, and importing a submodule runs its package."""
    edges = graph()
    assert "nerf_lightning.models" in edges["nerf_lightning.outputs.evaluation"] or any(
        target.startswith("nerf_lightning.models.") for target in edges["nerf_lightning.outputs.evaluation"])
    lazy = tmp_path / "lazy.py"
    lazy.write_text("def f():\n    from nerf_lightning.models.contract import RendersCamera\n")
    found = imported("nerf_lightning.lazy", lazy, modules())
    assert {"nerf_lightning.models", "nerf_lightning.models.contract"} <= found


def test_the_contract_imports_without_the_models():
    """What the commands read a model through loads none of the models (they load when a config names them)."""
    import subprocess
    import sys

    code = ("import sys, nerf_lightning.models.contract; "
            "print(sorted(m for m in sys.modules if m.startswith('nerf_lightning.models.')))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "['nerf_lightning.models.contract']"
