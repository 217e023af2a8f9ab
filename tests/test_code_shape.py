"""The shape of the code: no function in the repository's Python (the package, its tools,
``scripts/``, the tests, ``msg_adapters/``) is longer than MAX_LINES lines, so each reads as the
steps it is (a long one is split into helpers named after its steps), and no class of the
package is longer than MAX_CLASS_LINES lines (a longer one holds several jobs: split it by job).

A function's or class's length is ``end_lineno - lineno + 1`` of its ``def`` / ``class``
(decorators not counted; its docstring, comments and nested definitions are). The
generated-scene builders of ``data/synthetic/`` may stay long."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "sfm_ttr_ros"
MAX_LINES = 80
MAX_CLASS_LINES = 300
MAX_MODULE_LINES = 400  # core/stream/ and core/pipeline.py
EXEMPT_FOLDERS = ("sfm_ttr_ros/data/synthetic/",)
#: Folders of the checkout that hold no code of the project (environments, build and run outputs).
NOT_SOURCE = {"build", "install", "log", "out", "runs", "bench", "sfm_ttr_demo", "__pycache__"}
# Functions still longer than MAX_LINES, each with why; nothing else may join this list.
ALLOWED: set[str] = set()
def function_lengths(source: str) -> Iterator[tuple[str, int]]:
    """(qualified name, lines) of every function and method in ``source``, nested ones too."""
    return ((name.removesuffix("()"), n) for name, n in definition_lengths(source)
            if name.endswith("()"))


def class_lengths(source: str) -> Iterator[tuple[str, int]]:
    """(qualified name, lines) of every class in ``source``, nested ones too."""
    return ((name, n) for name, n in definition_lengths(source) if not name.endswith("()"))


def definition_lengths(source: str) -> Iterator[tuple[str, int]]:
    """(qualified name, lines) of every function (its name ending in ``()``) and class."""

    def walk(node: ast.AST, prefix: str) -> Iterator[tuple[str, int]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                name = prefix + child.name
                is_class = isinstance(child, ast.ClassDef)
                yield name + ("" if is_class else "()"), child.end_lineno - child.lineno + 1
                yield from walk(child, name + ".")
            else:
                yield from walk(child, prefix)

    yield from walk(ast.parse(source), "")


def source_files() -> Iterator[tuple[str, Path]]:
    """(path relative to the repository, path) of every Python file of the checkout outside the
    exempt folders and the folders that hold no source."""
    for path in sorted(REPO.rglob("*.py")):
        rel = path.relative_to(REPO)
        if any(p.startswith(".") or p in NOT_SOURCE or p.endswith(".egg-info")
               for p in rel.parts[:-1]):
            continue
        if not rel.as_posix().startswith(EXEMPT_FOLDERS):
            yield rel.as_posix(), path


def repo_functions() -> dict[str, int]:
    """``path:name`` -> lines, for every function of the repository's Python (paths of the
    package relative to ``sfm_ttr_ros/``, the others to the repository)."""
    out = {}
    for rel, path in source_files():
        short = rel.removeprefix("sfm_ttr_ros/")
        for name, lines in function_lengths(path.read_text()):
            out[f"{short}:{name}"] = lines
    return out


def package_classes() -> dict[str, int]:
    """``path:name`` -> lines, for every class of the package (paths relative to it)."""
    out = {}
    for rel, path in source_files():
        if rel.startswith("sfm_ttr_ros/"):
            for name, lines in class_lengths(path.read_text()):
                out[f"{rel.removeprefix('sfm_ttr_ros/')}:{name}"] = lines
    return out


def test_no_function_is_longer_than_the_limit():
    functions = repo_functions()
    too_long = {k: n for k, n in functions.items() if n > MAX_LINES and k not in ALLOWED}
    assert not too_long, (f"functions over {MAX_LINES} lines (split each into helpers named "
                          f"after its steps): {too_long}")
    stale = {k: functions.get(k) for k in ALLOWED if functions.get(k, 0) <= MAX_LINES}
    assert not stale, f"allowed long functions that are gone or short now (remove them): {stale}"


def test_no_class_is_longer_than_the_limit():
    classes = package_classes()
    too_long = {k: n for k, n in classes.items() if n > MAX_CLASS_LINES}
    assert not too_long, (f"classes over {MAX_CLASS_LINES} lines (split each by job): "
                          f"{too_long}")


def test_the_stream_and_the_window_pipeline_stay_short():
    """The stream's modules and the orchestrator are read first: each within MAX_MODULE_LINES."""
    package = REPO / "sfm_ttr_ros" / "core"
    modules = [*sorted((package / "stream").glob("*.py")), package / "pipeline.py"]
    too_long = {str(p.relative_to(REPO)): n for p in modules
                if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not too_long, f"modules over {MAX_MODULE_LINES} lines (split by job): {too_long}"


def test_the_check_sees_what_it_checks():
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES - 1))
    method_body = body.replace("\n", "\n    ")
    source = (f"@decorator\ndef fits():\n{body}\n\n\nclass C:\n    def method(self):\n"
              f"    {method_body}\n        x = 0\n\n        def inner():\n            return 1\n"
              f"\n    class Inner:\n        pass\n")
    lengths = dict(function_lengths(source))
    assert lengths["fits"] == MAX_LINES  # the decorator does not count
    assert lengths["C.method"] == MAX_LINES + 4 and lengths["C.method.inner"] == 2
    assert dict(class_lengths(source)) == {"C": MAX_LINES + 8, "C.Inner": 2}
    functions = repo_functions()
    assert "tools/benchmark/run.py:run_benchmark" in functions
    assert "ros/player.py:TopicRecorder.start" in functions
    assert "scripts/soak_node.py:main" in functions
    assert "tests/test_code_shape.py:test_the_check_sees_what_it_checks" in functions
    assert not any(k.startswith("data/synthetic/") for k in functions)
    classes = package_classes()
    assert "tools/benchmark/runners.py:ModeRun" in classes
    assert not any(k.startswith(".venv") for k in functions)


#: The documents' and the scripts folder's bounds: figures that must go go to docs/decisions.md
#: or the data folders (docs/benchmarks/), not into a longer BENCHMARKS.md.
DOC_LINES = {"README.md": 300, "BENCHMARKS.md": 600}
MAX_SCRIPTS = 8


def test_the_docs_and_scripts_stay_within_their_bounds():
    for name, limit in DOC_LINES.items():
        lines = len((REPO / name).read_text().splitlines())
        assert lines <= limit, f"{name} has {lines} lines (at most {limit})"
    scripts = sorted(p.name for p in (REPO / "scripts").iterdir()
                     if p.name != "README.md" and not p.name.startswith((".", "__")))
    assert len(scripts) <= MAX_SCRIPTS, f"scripts/ holds {len(scripts)} entries: {scripts}"
