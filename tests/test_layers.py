"""The package's layers (docs/architecture.md): imports go one way only.

    core  <-  data  <-  ros  <-  tools
      ^                  |
      +-- msg_adapters <-+

* (a) the core, the data sources and the CLI's ``run`` / ``benchmark`` / ``evaluate`` paths
  import and run with rclpy and every ROS message package blocked;
* (b) no module imports from a layer above its own (read from the source, every import,
  top-level and inside functions);
* (b') inside the core, a module imports from its own package or a lower rank of
  :data:`CORE_RANKS`, never up nor sideways (another package of its rank);
* (c) no import cycle between the package's modules (every import counts, ``if
  TYPE_CHECKING:`` ones too: a module that names another only for typing still couples them).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("sfm_ttr_ros", "msg_adapters")
LAYERS = ("core", "data", "ros", "tools")
# layer -> the layers it must not import from
FORBIDDEN = {
    "core": {"data", "ros", "tools", "msg_adapters"},
    "data": {"ros", "tools", "msg_adapters"},
    "msg_adapters": {"data", "ros", "tools"},
    "ros": {"tools"},
}
ROS_FREE_LAYERS = ("core", "data")  # not even a lazy import of a ROS package


def is_ros_package(module: str) -> bool:
    """rclpy, rcl_interfaces, builtin_interfaces and every ``*_msgs`` package (and theirs)."""
    top = module.split(".")[0]
    return top in ("rclpy", "rcl_interfaces", "builtin_interfaces") or top.endswith("_msgs")


# ---------------------------------------------------------------------------------------------
# The module graph, read from the source
# ---------------------------------------------------------------------------------------------


def module_files() -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package (packages as ``__init__``)."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            parts = list(path.relative_to(REPO).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


MODULES = module_files()


def layer_of(module: str) -> str:
    parts = module.split(".")
    if parts[0] == "msg_adapters":
        return "msg_adapters"
    if len(parts) > 1 and parts[1] in LAYERS:
        return parts[1]
    return "top"  # sfm_ttr_ros/__init__.py, __main__.py


def _resolve(module: str, importer: str, level: int, is_package: bool) -> str:
    if level == 0:
        return module
    base = importer.split(".") if is_package else importer.split(".")[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join([*base, module] if module else base)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _import_nodes(node: ast.AST, typing_only: bool = False) -> Iterator[tuple[ast.AST, bool]]:
    """Every Import / ImportFrom under ``node``, and whether it sits under ``if TYPE_CHECKING``."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.Import | ast.ImportFrom):
            yield child, typing_only
        elif isinstance(child, ast.If) and _is_type_checking(child.test):
            for stmt in child.body:
                yield from _import_nodes(ast.Module(body=[stmt], type_ignores=[]), True)
            for stmt in child.orelse:
                yield from _import_nodes(ast.Module(body=[stmt], type_ignores=[]), typing_only)
        else:
            yield from _import_nodes(child, typing_only)


def imports_of(module: str, runtime_only: bool = False) -> Iterator[tuple[str, int]]:
    """(imported module, line) for every import statement of ``module``, at any depth (top
    level, in functions; with ``runtime_only`` not those under ``if TYPE_CHECKING:``): a
    ``from a.b import c`` names ``a.b.c`` when that is a module of the package, else ``a.b``."""
    path = MODULES[module]
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    for node, typing_only in _import_nodes(tree):
        if runtime_only and typing_only:
            continue
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        else:
            base = _resolve(node.module or "", module, node.level, is_package)
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                yield (sub if sub in MODULES else base), node.lineno


def package_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports, typing-only imports included (itself left
    out)."""
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for module in MODULES:
        for target, _ in imports_of(module):
            while target and target not in MODULES:  # a name inside a module: its module
                target = target.rpartition(".")[0]
            if target and target != module:
                graph[module].add(target)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle (``[a, b, ..., a]``) of ``graph``, or None (iterative DFS)."""
    state: dict[str, int] = {}  # 1 = on the current path, 2 = done
    for root in sorted(graph):
        if root in state:
            continue
        path, stack = [root], [iter(sorted(graph[root]))]
        state[root] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return [*path[path.index(nxt):], nxt]
            elif nxt not in state:
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(sorted(graph[nxt])))
    return None


# ---------------------------------------------------------------------------------------------
# (b) layers, (c) cycles
# ---------------------------------------------------------------------------------------------


def test_every_layer_has_modules():
    """The layers this test checks exist (a renamed folder would make (b) pass vacuously)."""
    found = {layer_of(m) for m in MODULES}
    assert {"core", "data", "ros", "tools", "msg_adapters"} <= found
    assert "sfm_ttr_ros.core.frames" in MODULES and "msg_adapters.image" in MODULES


def test_no_import_goes_up_a_layer():
    wrong = []
    for module in MODULES:
        mine = layer_of(module)
        for target, line in imports_of(module):
            if target.split(".")[0] in PACKAGES and layer_of(target) in FORBIDDEN.get(mine, ()):
                wrong.append(f"{MODULES[module].relative_to(REPO)}:{line} ({mine}) imports "
                             f"{target} ({layer_of(target)})")
            elif mine in ROS_FREE_LAYERS and is_ros_package(target):
                wrong.append(f"{MODULES[module].relative_to(REPO)}:{line} ({mine}) imports the "
                             f"ROS package {target}")
    assert not wrong, "imports against the layering:\n" + "\n".join(wrong)


#: The core's own order, lowest first (docs/architecture.md, "The core"): a module imports from
#: its own package (``core/sfm/*`` from ``core/sfm``) or from a lower rank, never from another
#: package of its own rank (sideways) nor from a higher one (up). The basics (errors, outcomes
#: and threads below frames, the geometry, the networks, the colour maps and the evaluation);
#: the two branches of Fig. 2 that read the images (SfM, the network's prediction); the
#: alignment of the two; the stages that use the alignment (refinement, checks, metres); what a
#: window takes and gives; the camera path chaining windows; the orchestrator; the stream; the
#: schema reading every config.
CORE_RANKS = (
    ("errors", "outcomes", "threads"),
    ("frames", "geometry", "models", "visualize", "evaluation", "undistort"),
    ("sfm", "prediction"),
    ("alignment",),
    ("refinement", "checks", "metric"),
    ("window_io",),
    ("camera_path",),
    ("pipeline",),
    ("stream",),
    ("params",),
)


def core_package(module: str) -> str | None:
    """The core package (``sfm``, ``frames``, ...) of a module of the core; None outside it."""
    parts = module.split(".")
    if parts[:2] != ["sfm_ttr_ros", "core"] or len(parts) < 3:
        return None
    return parts[2]


def core_rank(module: str) -> int | None:
    package = core_package(module)
    if package is None:
        return None
    return next(i for i, names in enumerate(CORE_RANKS) if package in names)


def core_order_wrong(module: str, target: str) -> str | None:
    """``"up"`` when ``module`` imports ``target`` from a higher rank of the core, ``"sideways"``
    from another package of its own rank, None when the import follows the order (or either is
    outside the core)."""
    mine, theirs = core_rank(module), core_rank(target)
    if mine is None or theirs is None:
        return None
    if theirs > mine:
        return "up"
    if theirs == mine and core_package(target) != core_package(module):
        return "sideways"
    return None


def core_imports_against_the_order(way: str) -> list[str]:
    """Every import of the core that goes ``way`` (``up`` or ``sideways``), as file:line."""
    return [f"{MODULES[module].relative_to(REPO)}:{line} imports {target}"
            for module in MODULES for target, line in imports_of(module)
            if core_order_wrong(module, target) == way]


def test_every_core_module_has_a_rank():
    """A new core module or package gets a rank here (else the order tests skip it)."""
    top = {core_package(m) for m in MODULES if m.startswith("sfm_ttr_ros.core.")}
    ranked = [n for names in CORE_RANKS for n in names]
    assert len(ranked) == len(set(ranked)), "a core package in two ranks"
    assert top == set(ranked), "a core module without a rank, or a rank without a module"


def test_the_core_imports_downwards_stage_by_stage():
    """A stage never imports the orchestrator, the stream or the schema; the orchestrator never
    the stream; so each folder can be read without the ones above it."""
    wrong = core_imports_against_the_order("up")
    assert not wrong, "core imports up against its order:\n" + "\n".join(wrong)


def test_no_core_import_goes_sideways():
    """Packages of one rank never import each other (the SfM not the prediction, the checks not
    the refinement): what two of them share sits below both."""
    wrong = core_imports_against_the_order("sideways")
    assert not wrong, "core imports sideways within a rank:\n" + "\n".join(wrong)


def test_no_import_cycles():
    cycle = find_cycle(package_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_the_checks_see_what_they_check():
    """The graph tools on known shapes: a cycle is found, a relative import is resolved, and a
    module importing another from inside a function counts."""
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None
    assert _resolve("frames", "sfm_ttr_ros.core.pipeline", 1, False) == "sfm_ttr_ros.core.frames"
    assert _resolve("", "sfm_ttr_ros.data.synthetic", 1, True) == "sfm_ttr_ros.data.synthetic"
    # cli_bag imports evaluate_bag inside a function only
    assert "sfm_ttr_ros.ros.bag_evaluation" in package_graph()["sfm_ttr_ros.tools.cli_bag"]
    # render.py names SceneParams under TYPE_CHECKING only: a layer import, not a runtime one
    render = "sfm_ttr_ros.data.synthetic.render"
    typing_only = set(imports_of(render)) - set(imports_of(render, runtime_only=True))
    assert {target for target, _ in typing_only} == {"sfm_ttr_ros.data.synthetic.scene"}
    # the core's order: up, sideways, within a package, down; outside the core not its business
    core = "sfm_ttr_ros.core."
    assert core_order_wrong(core + "sfm.cloud", core + "alignment.scale") == "up"
    assert core_order_wrong(core + "checks.window", core + "refinement.encoder") == "sideways"
    assert core_order_wrong(core + "frames", core + "geometry") == "sideways"
    assert core_order_wrong(core + "checks.window", core + "checks.measures") is None
    assert core_order_wrong(core + "pipeline", core + "geometry") is None
    assert core_order_wrong(core + "sfm.result", "numpy") is None


# ---------------------------------------------------------------------------------------------
# (a) ROS blocked
# ---------------------------------------------------------------------------------------------

BLOCKED_RUN = r'''
import importlib, importlib.abc, io, pkgutil, sys, contextlib
from pathlib import Path

def is_ros_package(name):
    top = name.split(".")[0]
    return top in ("rclpy", "rcl_interfaces", "builtin_interfaces") or top.endswith("_msgs")

class BlockRos(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if is_ros_package(name):
            raise ImportError(f"{name} is blocked (the core and the CLI must run without ROS)")
        return None

sys.meta_path.insert(0, BlockRos())

import numpy as np, cv2
import sfm_ttr_ros.core, sfm_ttr_ros.data, sfm_ttr_ros.tools
for pkg in (sfm_ttr_ros.core, sfm_ttr_ros.data, sfm_ttr_ros.tools):
    for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
        importlib.import_module(info.name)

from sfm_ttr_ros.tools.cli import build_parser, main
parser = build_parser()
for command in ("run", "benchmark", "evaluate"):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        try:
            parser.parse_args([command, "-h"])
        except SystemExit as exc:
            assert exc.code == 0, (command, exc.code)
    assert "usage: sfm-ttr " + command in out.getvalue(), out.getvalue()

# evaluate, folder mode, on two tiny folders: GT 10 m, prediction 11 m (abs rel 0.1)
root = Path(sys.argv[1])
pred, gt = root / "pred", root / "gt"
pred.mkdir(); gt.mkdir()
for name in ("0000000000", "0000000001"):
    cv2.imwrite(str(gt / f"{name}.png"), np.full((8, 12), 2560, np.uint16))
    np.save(pred / f"{name}.npy", np.full((8, 12), 11.0, np.float32))
out = io.StringIO()
with contextlib.redirect_stdout(out):
    code = main(["evaluate", "--pred", str(pred), "--gt", str(gt), "--no-median-scaling",
                 "--out", str(root / "eval.json")])
assert code == 0, (code, out.getvalue())
assert "2 frames evaluated" in out.getvalue(), out.getvalue()
import json
res = json.loads((root / "eval.json").read_text())["results"]["pred"]
assert abs(res["abs_rel"] - 0.1) < 1e-6, res

leaked = sorted(m for m in sys.modules if is_ros_package(m))
assert not leaked, leaked
print("ROS-free:", len([m for m in sys.modules if m.startswith("sfm_ttr_ros.")]), "modules")
'''


@pytest.mark.slow
def test_core_and_cli_run_with_ros_blocked(tmp_path):
    """Every module of core/, data/ and tools/ imports, ``sfm-ttr run|benchmark|evaluate -h``
    parse and ``sfm-ttr evaluate`` scores two folders, with rclpy, rcl_interfaces,
    builtin_interfaces and every ``*_msgs`` package unimportable."""
    proc = subprocess.run([sys.executable, "-c", BLOCKED_RUN, str(tmp_path)], cwd=REPO,
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-6000:]
    assert "ROS-free:" in proc.stdout
