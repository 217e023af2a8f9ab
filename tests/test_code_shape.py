"""The shape of the code: no function of the package is longer than MAX_LINES lines, so each
reads as the steps it is (a long one is split into helpers named after its steps).

A function's length is ``end_lineno - lineno + 1`` of its ``def`` (decorators not counted; its
docstring, comments and nested functions are). The generated-scene builders of
``data/synthetic/`` may stay long."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "sfm_ttr_ros"
MAX_LINES = 80
EXEMPT_FOLDERS = ("data/synthetic/",)
# Functions still longer than MAX_LINES, each with why; nothing else may join this list.
ALLOWED: set[str] = set()


def function_lengths(source: str) -> Iterator[tuple[str, int]]:
    """(qualified name, lines) of every function and method in ``source``, nested ones too."""

    def walk(node: ast.AST, prefix: str) -> Iterator[tuple[str, int]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = prefix + child.name
                yield name, child.end_lineno - child.lineno + 1
                yield from walk(child, name + ".")
            elif isinstance(child, ast.ClassDef):
                yield from walk(child, prefix + child.name + ".")
            else:
                yield from walk(child, prefix)

    yield from walk(ast.parse(source), "")


def package_functions() -> dict[str, int]:
    """``path:name`` -> lines, for every function of the package outside the exempt folders."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel.startswith(EXEMPT_FOLDERS):
            continue
        for name, lines in function_lengths(path.read_text()):
            out[f"{rel}:{name}"] = lines
    return out


def test_no_function_is_longer_than_the_limit():
    functions = package_functions()
    too_long = {k: n for k, n in functions.items() if n > MAX_LINES and k not in ALLOWED}
    assert not too_long, (f"functions over {MAX_LINES} lines (split each into helpers named "
                          f"after its steps): {too_long}")
    stale = {k: functions.get(k) for k in ALLOWED if functions.get(k, 0) <= MAX_LINES}
    assert not stale, f"allowed long functions that are gone or short now (remove them): {stale}"


def test_the_check_sees_what_it_checks():
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES - 1))
    method_body = body.replace("\n", "\n    ")
    source = (f"@decorator\ndef fits():\n{body}\n\n\nclass C:\n    def method(self):\n"
              f"    {method_body}\n        x = 0\n\n        def inner():\n            return 1\n")
    lengths = dict(function_lengths(source))
    assert lengths["fits"] == MAX_LINES  # the decorator does not count
    assert lengths["C.method"] == MAX_LINES + 4 and lengths["C.method.inner"] == 2
    functions = package_functions()
    assert "tools/benchmark/run.py:run_benchmark" in functions
    assert "ros/player.py:TopicRecorder.start" in functions
    assert not any(k.startswith("data/synthetic/") for k in functions)
