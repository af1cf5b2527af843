"""The package's layering: which stage may import which (read from the source, imports inside functions too).

    core -> objects -> sensor / simulate / patches -> network / rig -> training
                                                    network -> localize -> pose -> tracking -> evaluation
Inference (localize, pose, evaluation) never imports training. Command-line wrappers (`*/cli.py`, `yoto/cli.py`,
`yoto/demo.py`) compose every stage and sit on top. No two modules import each other at import time.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "yoto"

CORE = {"errors", "workspace", "io", "geometry", "pointcloud", "raycast", "registration", "provenance", "metrics"}
CORE |= {"contacts", "trajectory", "tactile_image", "jit"}
RANK = {
    **{name: 0 for name in CORE},
    "objects": 1,
    "sensor": 2,
    "patches": 2,
    "simulate": 2,
    "network": 3,
    "rig": 3,  # recordings in: calibration chain, bags, labelling (reads sensor images, writes contact files)
    "training": 4,
    "localize": 4,
    "pose": 5,
    "tracking": 6,  # after the touch: needs the pose stage's estimate
    "evaluation": 7,
}
TOP = 99  # command-line wrappers and the demo
INFERENCE = {"localize", "pose", "tracking", "evaluation", "rig"}


def stage_of(module: str) -> str:
    """'yoto.localize.match.anchors' -> 'localize'; 'yoto' -> '' (the package face)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def rank_of(module: str) -> int:
    parts = module.split(".")
    if parts[-1] in ("cli", "demo", "__main__"):
        return TOP
    stage = stage_of(module)
    if stage == "":
        return 0
    if stage not in RANK:
        raise AssertionError(f"{module}: stage '{stage}' has no place in the layering; add it to RANK")
    return RANK[stage]


def module_name(path: Path) -> str:
    relative = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(relative.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def yoto_imports(path: Path) -> list[tuple[str, bool]]:
    """(imported yoto module, at module level?) for every import in a file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    module_level = set(map(id, tree.body))
    found = []
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
        for name in names:
            if name == "yoto" or name.startswith("yoto."):
                found.append((name, id(node) in module_level))
    return found


MODULES = {module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_run_down_the_layers(module):
    importer_rank = rank_of(module)
    for imported, _ in yoto_imports(MODULES[module]):
        if imported == "yoto" or stage_of(imported) == stage_of(module):
            continue
        assert rank_of(imported) <= importer_rank, (
            f"{module} (rank {importer_rank}) imports {imported} (rank {rank_of(imported)}): arrows must run down"
        )
        if stage_of(module) in INFERENCE or stage_of(module) == "network":
            assert stage_of(imported) != "training", f"{module} imports {imported}: inference never imports training"


def test_no_import_cycles_at_module_level():
    graph = {
        module: {name for name, top in yoto_imports(path) if top and name in MODULES and name != module}
        for module, path in MODULES.items()
    }
    state: dict[str, int] = {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = trail[trail.index(nxt) :] + [nxt] if nxt in trail else [node, nxt]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt, trail + [nxt])
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])


def test_the_layering_catches_a_wrong_arrow(tmp_path):
    """The checks above can fail: a core module importing the pose stage is ranked as a wrong arrow."""
    assert rank_of("yoto.geometry") < rank_of("yoto.pose.solver")
    assert rank_of("yoto.localize.network") == rank_of("yoto.training.loop")
    source = tmp_path / "probe.py"
    source.write_text(
        "import numpy\nfrom yoto.pose.solver import solve_pose\n\n\ndef f():\n    import yoto.training.cli\n"
    )
    assert yoto_imports(source) == [("yoto.pose.solver", True), ("yoto.training.cli", False)]
