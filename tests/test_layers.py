"""The package's layers import strictly downwards: each module of jaxmm imports only from the
layers its own layer stands on (``LAYERS``), read from the source by ``ast``, so that the
rigid-body library stays usable alone and the solver knows nothing of robots."""

import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "jaxmm"

# Each layer and the layers it may import from, bottom first. The solver sees only the stage-wise
# problem interface; the rigid-body library nothing but itself.
LAYERS = {
    "compilation": set(),
    "rigid_body": set(),
    "robots": {"rigid_body"},
    "physics": set(),
    "stagewise": set(),
    "transcription": {"rigid_body", "robots", "physics", "stagewise"},
    "tasks": {"rigid_body", "robots", "transcription"},
    "solver": {"stagewise"},
    "analysis": {"rigid_body", "robots", "physics", "transcription", "tasks", "solver"},
    "programs": {"compilation", "stagewise", "transcription", "tasks", "solver"},
    "solve": {"programs", "solver", "transcription", "tasks", "analysis"},
    "schedule": {"compilation", "programs", "solver"},
    "batch": {"programs", "schedule", "solve", "solver", "transcription", "tasks", "analysis"},
    "tuning": {"solve", "solver"},
    "io": {"rigid_body", "robots", "transcription", "solver", "programs"},
    "reference": {"rigid_body", "robots", "physics", "transcription", "tasks"},
    "cli": {"compilation", "robots", "tasks", "solver", "analysis", "programs", "batch", "io", "reference", "jaxmm"},
    "__main__": {"cli"},
}


def layer_of(module):
    """The layer of a dotted module name inside jaxmm (``jaxmm.solver.linalg`` → ``solver``)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "jaxmm"


def imported_modules(path):
    """The jaxmm modules that the source file ``path`` imports (at any depth of its code)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names if alias.name.split(".")[0] == "jaxmm"}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "jaxmm":  # `from jaxmm import x`: x is a submodule, or the top level's
                found |= {f"jaxmm.{alias.name}" if (PACKAGE / alias.name).exists()
                          or (PACKAGE / f"{alias.name}.py").exists() else "jaxmm" for alias in node.names}
            elif node.module.split(".")[0] == "jaxmm":
                found.add(node.module)
    return found


MODULES = sorted(p for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" or p.parent != PACKAGE)


def test_every_module_belongs_to_a_layer():
    names = {layer_of("jaxmm." + ".".join(p.relative_to(PACKAGE).with_suffix("").parts)) for p in MODULES}
    assert names <= set(LAYERS), f"modules outside every layer: {sorted(names - set(LAYERS))}"


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_go_downwards(path):
    own = layer_of("jaxmm." + ".".join(path.relative_to(PACKAGE).with_suffix("").parts))
    allowed = LAYERS[own] | {own}
    wrong = sorted(m for m in imported_modules(path) if layer_of(m) not in allowed)
    assert not wrong, f"{path.relative_to(PACKAGE)} (layer {own}) imports from layers above it: {wrong}"


def test_the_reader_sees_an_upward_import(tmp_path):
    source = tmp_path / "upward.py"
    source.write_text("from jaxmm.transcription import nlp\nfrom jaxmm import tasks, so3\nimport jaxmm.robots.meshes\n")
    assert imported_modules(source) == {"jaxmm.transcription", "jaxmm.tasks", "jaxmm", "jaxmm.robots.meshes"}


ROOT = PACKAGE.parent


def test_no_private_name_is_used_outside_its_module():
    """``from m import _x`` and ``m._x`` for a jaxmm module ``m`` appear nowhere in the package,
    its tests, benchmarks or tools."""
    found = []
    for path in [*PACKAGE.rglob("*.py"), *(ROOT / "tests").glob("*.py"), *(ROOT / "benchmarks").glob("*.py"),
                 *(ROOT / "tools").glob("*.py")]:
        tree = ast.parse(path.read_text())
        aliases = {alias.asname or alias.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                   and (node.module or "").startswith("jaxmm") for alias in node.names}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("jaxmm"):
                assert not [a.name for a in node.names if a.name.startswith("_") and a.name != "__version__"], path
            if isinstance(node, ast.ImportFrom) and node.module and not node.module.startswith("jaxmm"):
                assert not [a.name for a in node.names if a.name.startswith("_")], path
            if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                if isinstance(node.value, ast.Name) and node.value.id in aliases:
                    found.append(f"{path.relative_to(ROOT)}: {node.value.id}.{node.attr}")
    assert not found, found
