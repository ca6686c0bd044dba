"""docs/spot.md cannot go stale silently: every ``module:function`` it names imports and resolves,
links to the module's own file, every ``tests/file.py::test_name`` is a test function in that file
(read from its AST), every fidelity row it cites is a row of docs/fidelity.md, and every equation
section names at least one function and one test. The checker itself is tested on a broken page."""

import ast
import importlib
import os
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGE = REPO / "docs" / "spot.md"
FIDELITY = REPO / "docs" / "fidelity.md"

# The learning core the page walks through: each module must be cited at least once.
CORE = (
    "spot.reward.pt",
    "spot.reward.train",
    "spot.subgoal.extract",
    "spot.subgoal.cvae",
    "spot.subgoal.shaping",
    "spot.policy.iql",
)

CODE = re.compile(r"`(spot(?:\.\w+)*):(\w+(?:\.\w+)*)`")  # `spot.reward.pt:PreferenceTransformer.attention`
TEST = re.compile(r"`(tests/[\w/]+\.py)::(\w+(?:::\w+)*)`")  # `tests/test_reward.py::test_pref_loss_by_hand`
LINKED = re.compile(r"\[`([^`]+)`\]\(([^)\s]+)\)")  # [`ref`](path)
ROW = re.compile(r"\[rows? (\d+)(?:-(\d+))?\]\(fidelity\.md#the-matrix\)")


def _resolve(module: str, attr: str) -> str | None:
    """Why ``module:attr`` does not resolve to something callable, or None when it does."""
    try:
        obj = importlib.import_module(module)
    except ImportError as e:
        return f"cannot import {module} ({e})"
    for part in attr.split("."):
        if not hasattr(obj, part):
            return f"{module} has no {attr}"
        obj = getattr(obj, part)
    return None if callable(obj) else f"{module}:{attr} is not a function or class"


def _test_names(path: Path) -> set[str]:
    """``name`` of every test function and ``Class::name`` of every test method in a test file."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            names.add(node.name)
        elif isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef):
                    names.add(f"{node.name}::{item.name}")
    return names


def _fidelity_rows(fidelity: Path) -> set[int]:
    return {int(m) for m in re.findall(r"^\| (\d+) \|", fidelity.read_text(), flags=re.M)}


def _sections(text: str) -> list[tuple[str, str]]:
    """``(heading, body)`` of every ``## `` section."""
    parts = re.split(r"^## (.+)$", text, flags=re.M)
    return list(zip(parts[1::2], parts[2::2], strict=True))


def problems(page: Path, root: Path = REPO, fidelity: Path = FIDELITY) -> list[str]:
    """Every stale or malformed reference of ``page`` (paths relative to ``root``), one line each."""
    text = page.read_text()
    out = []
    links = {(m.start(), m.group(1)): m.group(2) for m in LINKED.finditer(text)}
    for m in CODE.finditer(text):
        module, attr = m.groups()
        ref = f"{module}:{attr}"
        if (why := _resolve(module, attr)) is not None:
            out.append(f"{ref}: {why}")
            continue
        target = links.get((m.start() - 1, ref))
        if target is None:
            out.append(f"{ref}: not a link to its file")
            continue
        module_file = Path(importlib.import_module(module).__file__).resolve()
        if (page.parent / target).resolve() != module_file:
            out.append(f"{ref}: links to {target}, but the module is {module_file.relative_to(REPO)}")
    for m in TEST.finditer(text):
        path, name = m.groups()
        ref = f"{path}::{name}"
        test_file = root / path
        if not test_file.is_file():
            out.append(f"{ref}: no file {path}")
        elif name not in _test_names(test_file):
            out.append(f"{ref}: no test {name} in {path}")
        elif (target := links.get((m.start() - 1, ref))) is None:
            out.append(f"{ref}: not a link to its file")
        elif (page.parent / target).resolve() != test_file.resolve():
            out.append(f"{ref}: links to {target}, not to {path}")
    rows = _fidelity_rows(fidelity)
    for m in ROW.finditer(text):
        first, last = int(m.group(1)), int(m.group(2) or m.group(1))
        missing = [n for n in range(first, last + 1) if n not in rows]
        if missing or last < first:
            out.append(f"{m.group(0)}: no such row(s) {missing or [first, last]} in {fidelity.name}")
    for heading, body in _sections(text):
        if "eq." in heading and not (CODE.search(body) and TEST.search(body)):
            out.append(f"section '{heading}': names no function or no test")
    return out


def test_every_reference_on_the_spot_page_exists():
    found = problems(PAGE)
    assert not found, "docs/spot.md is stale:\n" + "\n".join(found)


def test_the_spot_page_covers_the_learning_core_and_each_equation():
    text = PAGE.read_text()
    cited = {m.group(1) for m in CODE.finditer(text)}
    assert not set(CORE) - cited, f"docs/spot.md cites nothing of {sorted(set(CORE) - cited)}"
    assert len({m.groups() for m in TEST.finditer(text)}) >= 20
    headings = " ".join(h for h, _ in _sections(text))
    for eq in ("eq. 1-4", "eq. 4-6", "eq. 7-9", "eq. 10", "eq. 11-13"):
        assert eq in headings, f"no section of docs/spot.md is headed with {eq}"
    assert "IQL" in headings


def test_the_checker_finds_each_kind_of_stale_reference(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_x.py").write_text(
        "def test_ok():\n    pass\n\n\nclass TestC:\n    def test_m(self):\n        pass\n"
    )
    fidelity = tmp_path / "docs" / "fidelity.md"
    fidelity.write_text("| # | choice |\n|---|---|\n| 1 | a |\n| 2 | b |\n")
    pt = os.path.relpath(REPO / "spot" / "reward" / "pt.py", tmp_path / "docs")
    page = tmp_path / "docs" / "page.md"
    page.write_text(
        f"## Good (eq. 1)\n[`spot.reward.pt:forward`]({pt}) "
        "[`tests/test_x.py::test_ok`](../tests/test_x.py) [`tests/test_x.py::TestC::test_m`](../tests/test_x.py) "
        "[rows 1-2](fidelity.md#the-matrix)\n"
        "## Bad (eq. 2)\n"
        f"[`spot.reward.pt:no_such_function`]({pt}) `spot.reward.pt:attention` "
        "[`spot.no_such_module:f`](x.py) [`spot.reward.pt:PT.init`](../spot/reward/mr.py) "
        "[`tests/test_x.py::test_gone`](../tests/test_x.py) [`tests/test_y.py::test_ok`](../tests/test_y.py) "
        "[`tests/test_x.py::test_ok`](../tests/test_z.py) [row 3](fidelity.md#the-matrix)\n"
        "## Empty (eq. 3)\nnothing here\n"
    )
    found = problems(page, tmp_path, fidelity)
    expected = [
        "spot.reward.pt:no_such_function: spot.reward.pt has no no_such_function",
        "spot.reward.pt:attention: not a link to its file",
        "spot.no_such_module:f: cannot import spot.no_such_module",
        "spot.reward.pt:PT.init: links to ../spot/reward/mr.py, but the module is spot/reward/pt.py",
        "tests/test_x.py::test_gone: no test test_gone in tests/test_x.py",
        "tests/test_y.py::test_ok: no file tests/test_y.py",
        "tests/test_x.py::test_ok: links to ../tests/test_z.py, not to tests/test_x.py",
        "[row 3](fidelity.md#the-matrix): no such row(s) [3] in fidelity.md",
        "section 'Empty (eq. 3)': names no function or no test",
    ]
    assert len(found) == len(expected), "\n".join(found)
    for line, want in zip(found, expected, strict=True):
        assert line.startswith(want), (line, want)


@pytest.mark.parametrize("ref", ["spot.reward.pt:PreferenceTransformer.attention", "spot.policy.iql:update"])
def test_resolve_accepts_functions_and_methods(ref):
    assert _resolve(*ref.split(":")) is None
