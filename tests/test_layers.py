"""Layers point down: no spot module imports a module of a higher layer (docs/design.md, "Module layers").

Every import counts, at module level or inside a function, and so does ``importlib.import_module``
of a literal ``spot.`` name (an f-string's literal prefix included). Modules of one layer may import
each other, except where a level holds several layers: ``spot.reward``, ``spot.subgoal`` and
``spot.policy`` are independent of one another.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# (level, layer, module prefixes), lowest first. A module belongs to the layer with its longest prefix.
LAYERS = [
    (
        0,
        "base",
        [
            "spot",
            "spot.runtime",
            "spot.phases",
            "spot.batches",
            "spot.nets",
            "spot.loop",
            "spot.codeversion",
            "spot.cache",
            "spot.store",
        ],
    ),
    (1, "data", ["spot.data"]),
    (2, "config", ["spot.config"]),
    (3, "envs", ["spot.envs", "spot.evaluation", "spot.mujoco_step"]),
    (4, "reward", ["spot.reward"]),
    (4, "subgoal", ["spot.subgoal"]),
    (4, "policy", ["spot.policy"]),
    (5, "recipes", ["spot.recipes"]),
    (6, "tracking", ["spot.tracking"]),
    (7, "stages", ["spot.run", "spot.stages", "spot.pipeline"]),
    (
        8,
        "apps",
        [
            "spot.sweep",
            "spot.tables",
            "spot.figures",
            "spot.bench",
            "spot.bench_programs",
            "spot.results",
            "spot.report",
            "spot.stats",
        ],
    ),
    (9, "cli", ["spot.cli"]),
]

# Late-bound lookups by name that cross layers on purpose, with the reason (docs/design.md).
LATE_BOUND = {
    ("spot.data.registry", "spot.recipes"): "registry.build runs the recipe a registered dataset name maps "
    "to, by module name (Entry.recipe); spot.data imports no recipe",
}


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer_of(module: str) -> tuple[int, str] | None:
    best = None
    for level, name, prefixes in LAYERS:
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and (best is None or len(p) > best[0]):
                best = (len(p), level, name)
    return None if best is None else best[1:]


def imports_of(source: str, module: str, is_package: bool, known: set[str]) -> list[tuple[int, str, bool]]:
    """``(line, imported spot module, late_bound)`` for every import in ``source``."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, False) for a in node.names if a.name.split(".")[0] == "spot"]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = module.split(".") if is_package else module.split(".")[:-1]
                pkg = pkg[: len(pkg) - (node.level - 1)]
                base = ".".join(pkg + ([base] if base else []))
            if base.split(".")[0] == "spot":
                for a in node.names:
                    sub = f"{base}.{a.name}"
                    out.append((node.lineno, sub if sub in known else base, False))
        elif (
            isinstance(node, ast.Call)
            and node.args
            and ast.unparse(node.func) in ("importlib.import_module", "import_module")
        ):
            arg = node.args[0]
            literal = (
                arg.value
                if isinstance(arg, ast.Constant)
                else (
                    arg.values[0].value
                    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant)
                    else ""
                )
            )
            if isinstance(literal, str) and literal.startswith("spot"):
                out.append((node.lineno, literal.rstrip("."), True))
    return out


def violations(sources: dict[str, tuple[str, bool]]) -> list[str]:
    """Upward (or sideways, between independent layers) imports among ``{module: (source, is_package)}``."""
    known = set(sources)
    found = []
    for module, (source, is_package) in sorted(sources.items()):
        here = layer_of(module)
        for line, target, late in imports_of(source, module, is_package, known):
            there = layer_of(target)
            if there is None or target == module or there[1] == here[1] or there[0] < here[0]:
                continue
            if late and any(target == t or target.startswith(t + ".") for (m, t) in LATE_BOUND if m == module):
                continue
            found.append(
                f"{module}:{line} ({here[1]}, level {here[0]}) imports {target} ({there[1]}, level {there[0]})"
            )
    return found


def _spot_sources() -> dict[str, tuple[str, bool]]:
    return {module_name(p): (p.read_text(), p.name == "__init__.py") for p in sorted((ROOT / "spot").rglob("*.py"))}


def test_every_module_has_a_layer():
    missing = sorted(m for m in _spot_sources() if layer_of(m) is None)
    assert not missing, f"modules without a layer (add them to LAYERS and docs/design.md): {missing}"


def test_no_module_imports_a_higher_layer():
    found = violations(_spot_sources())
    assert not found, "imports that point up:\n" + "\n".join(found)


def test_data_imports_neither_policy_nor_envs():
    sources = _spot_sources()
    known = set(sources)
    for module, (source, is_package) in sources.items():
        if module.startswith("spot.data"):
            targets = {
                t
                for _, t, late in imports_of(source, module, is_package, known)
                if not (late and (module, t) in LATE_BOUND)
            }
            assert not {t for t in targets if t.startswith(("spot.policy", "spot.envs", "spot.recipes"))}, module


def test_the_late_bound_lookups_still_exist():
    """An allowance whose lookup is gone must be removed, not kept as a blanket exception."""
    sources = _spot_sources()
    for module, target in LATE_BOUND:
        source, is_package = sources[module]
        assert any(late and t.startswith(target) for _, t, late in imports_of(source, module, is_package, set(sources)))


@pytest.mark.parametrize(
    "source, expected",
    [
        ("from spot.policy import sac\n", ["spot.data.x:1 (data, level 1) imports spot.policy.sac (policy, level 4)"]),
        ("def f():\n    from spot import envs\n", ["spot.data.x:2 (data, level 1) imports spot.envs (envs, level 3)"]),
        ("import spot.stages\n", ["spot.data.x:1 (data, level 1) imports spot.stages (stages, level 7)"]),
        ("from ..envs import make_env\n", ["spot.data.x:1 (data, level 1) imports spot.envs (envs, level 3)"]),
        (
            "import importlib\nm = importlib.import_module(f'spot.policy.{name}')\n",
            ["spot.data.x:2 (data, level 1) imports spot.policy (policy, level 4)"],
        ),
        ("from spot.data import dataset\nfrom spot import SpotError, batches\n", []),  # same layer, below
    ],
)
def test_the_checker_sees_upward_imports(source, expected):
    known = {
        "spot",
        "spot.data",
        "spot.data.x",
        "spot.data.dataset",
        "spot.policy",
        "spot.policy.sac",
        "spot.envs",
        "spot.stages",
        "spot.batches",
    }
    sources = {m: ("", m in ("spot", "spot.data", "spot.policy")) for m in known}
    sources["spot.data.x"] = (source, False)
    assert violations(sources) == expected


def test_independent_layers_of_one_level_do_not_import_each_other():
    sources = {
        "spot.reward.x": ("from spot.policy import iql\n", False),
        "spot.policy.iql": ("", False),
        "spot.subgoal.y": ("from spot.subgoal import cvae\nfrom spot import nets\n", False),
        "spot.subgoal.cvae": ("", False),
        "spot.nets": ("", False),
    }
    assert violations(sources) == ["spot.reward.x:1 (reward, level 4) imports spot.policy.iql (policy, level 4)"]
