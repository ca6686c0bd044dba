"""The structure the docs promise: a short `run`, short functions (or a documented reason)."""

import ast
import inspect
import re
from pathlib import Path

from spot import pipeline

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 80


def _documented_long_functions() -> dict[str, str]:
    """``module:function -> reason`` from docs/design.md's "Long functions" list."""
    text = (ROOT / "docs" / "design.md").read_text()
    section = text.split("### Long functions", 1)[1].split("\n## ", 1)[0]
    return dict(re.findall(r"^\* `([\w/.]+:\w+)`: (.+)$", section, flags=re.M))


def _long_functions() -> dict[str, int]:
    out = {}
    for path in sorted((ROOT / "spot").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_LINES:
                    out[f"{path.relative_to(ROOT).as_posix()}:{node.name}"] = n
    return out


def test_run_reads_as_the_data_flow():
    assert len(inspect.getsource(pipeline.run).splitlines()) <= 40


def test_no_function_over_80_lines_unless_the_docs_say_why():
    documented = _documented_long_functions()
    long = _long_functions()
    undocumented = {k: n for k, n in long.items() if k not in documented}
    assert not undocumented, f"functions over {MAX_LINES} lines without a reason in docs/design.md: {undocumented}"
    stale = sorted(set(documented) - set(long))
    assert not stale, f"docs/design.md lists functions that are no longer long (remove them): {stale}"


def test_the_checker_sees_a_long_function(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES))
    node = ast.parse(f"def f():\n{body}\n").body[0]
    assert node.end_lineno - node.lineno + 1 > MAX_LINES


MAX_MODULE_LINES = 500


def _documented_long_modules() -> dict[str, str]:
    """``spot/path.py -> reason`` from docs/design.md's "Long modules" list."""
    text = (ROOT / "docs" / "design.md").read_text()
    assert "### Long modules" in text, "docs/design.md lacks its 'Long modules' section"
    section = text.split("### Long modules", 1)[1].split("\n## ", 1)[0].split("\n### ", 1)[0]
    return dict(re.findall(r"^\* `(spot/[\w/.]+\.py)`: (.+)$", section, flags=re.M))


def _long_modules() -> dict[str, int]:
    out = {}
    for path in sorted((ROOT / "spot").rglob("*.py")):
        n = len(path.read_text().splitlines())
        if n > MAX_MODULE_LINES:
            out[path.relative_to(ROOT).as_posix()] = n
    return out


def test_no_module_over_the_cap_unless_the_docs_say_why():
    documented = _documented_long_modules()
    long = _long_modules()
    undocumented = {k: n for k, n in long.items() if k not in documented}
    assert not undocumented, f"modules over {MAX_MODULE_LINES} lines without a reason in docs/design.md: {undocumented}"
    stale = sorted(set(documented) - set(long))
    assert not stale, f"docs/design.md lists modules that are no longer long (remove them): {stale}"
