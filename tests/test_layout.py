"""The layout tells the truth: stages are peers that never import one another, and the simulator never imports torch.

Imports are read from the source (every ``import`` statement, including ones inside functions), so a lazy import
of another stage cannot hide from the check.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
STAGES = ("collect", "train_vae", "train_rnn", "demonstrate", "train_agent", "evaluate", "ncap")


def imported_modules(path: Path, package: str) -> set[str]:
    """Absolute names of every module ``path`` imports (relative imports resolved against ``package``)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parent, base] if base else parent)
            found.add(base)
            found |= {f"{base}.{alias.name}" for alias in node.names}  # `from . import train_vae`
    return found


@pytest.mark.parametrize("stage", STAGES)
def test_a_stage_never_imports_another_stage(stage):
    imports = imported_modules(ROOT / "worldmodel" / f"{stage}.py", "worldmodel")
    others = {f"worldmodel.{s}" for s in STAGES if s != stage} | {"worldmodel.pipeline"}
    assert not imports & others, f"worldmodel/{stage}.py imports {sorted(imports & others)}: go through artifacts"


def test_the_check_sees_lazy_and_relative_imports(tmp_path):
    """The check itself can fail: a stage-to-stage import inside a function, in either spelling, is found."""
    src = tmp_path / "fake_stage.py"
    src.write_text("def run(cfg):\n    from .train_vae import load_vae\n    from . import evaluate\n")
    imports = imported_modules(src, "worldmodel")
    assert {"worldmodel.train_vae", "worldmodel.evaluate"} <= imports


def test_only_the_pipeline_knows_every_stage():
    helpers = [p for p in (ROOT / "worldmodel").glob("*.py") if p.stem not in (*STAGES, "pipeline")]
    for path in helpers:
        imports = imported_modules(path, "worldmodel")
        stages = sorted(imports & {f"worldmodel.{s}" for s in STAGES})
        assert not stages, f"{path.name} imports the stage modules {stages}; shared code belongs in artifacts/common"


def test_the_simulator_never_imports_torch():
    for path in (ROOT / "envs").glob("*.py"):
        imports = imported_modules(path, "envs")
        assert not {m for m in imports if m == "torch" or m.startswith("torch.")}, path


def test_collection_and_the_configs_load_without_torch():
    """Collection is numpy and pybullet: its spawned workers and the typed configs every stage reads load no torch,
    which costs each worker about a second and 200 MB."""
    probe = "import sys, worldmodel.collect, worldmodel.config; print(sorted(m for m in sys.modules if m == 'torch'))"
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def family_sources(family: str) -> list[tuple[Path, str]]:
    """(path, package its relative imports resolve against) of every module of family ``family``'s package."""
    paths = sorted((ROOT / "worldmodel" / "families" / family).rglob("*.py"))
    return [(path, ".".join(path.parent.relative_to(ROOT).parts)) for path in paths]


def test_every_family_keeps_the_interface_and_imports_no_other_family():
    """Each registered family is declared by its own package, runs a module with the System interface
    (worldmodel/registry.py), its paper's preset sets up that family, and none of its modules imports another
    family."""
    from worldmodel import registry
    from worldmodel.config import preset_globals

    names = set(registry.names())
    assert registry.default().name == "porav"
    for family in registry.families():
        assert family.system.startswith(f"worldmodel.families.{family.name}."), family.system
        module = registry.system(family.name)
        assert isinstance(module, registry.System), family.name
        if family.learners or family.observations:
            assert isinstance(module, registry.Trainer), family.name
        if family.preset:
            assert preset_globals(family.preset)["env"]["family"] == family.name
        others = tuple(f"worldmodel.families.{n}" for n in names - {family.name})
        sources = family_sources(family.name)
        assert sources, f"no source for family {family.name}"
        for path, package in sources:
            imports = imported_modules(path, package)
            bad = sorted(m for m in imports if m in others or m.startswith(tuple(f"{o}." for o in others)))
            where = path.relative_to(ROOT / "worldmodel")
            assert not bad, f"{where} imports {bad}: share through families/common.py"
    with pytest.raises(KeyError, match="known are porav, chae, kim, merola"):
        registry.family("ncap")


def test_the_schema_holds_each_declared_familys_sections_from_its_own_package():
    """``agent.<section>`` and ``evaluate.<section>`` are the dataclasses the family declares in its package's
    config.py, composed at their defaults; a family registered at run time cannot add sections to a schema built
    already, and is told where to declare it."""
    import dataclasses

    from worldmodel import registry
    from worldmodel.config import AgentConfig, EvaluateConfig, compose

    cfg = compose("train_agent")
    for family in registry.families():
        for schema, part, declared in (
            (AgentConfig, "agent", family.agent_config),
            (EvaluateConfig, "evaluate", family.eval_config),
        ):
            if declared is None:
                continue
            assert declared.__module__ == f"worldmodel.families.{family.name}.config"
            types = {f.name: f.default_factory for f in dataclasses.fields(schema)}
            assert types[family.section] is declared
            assert dict(cfg[part][family.section]) == dataclasses.asdict(declared())
    late = dataclasses.replace(registry.default(), name="late", section="late", eval_config=EvaluateConfig)
    with pytest.raises(ValueError, match="DECLARED"):
        registry.register(late)
    assert "late" not in registry.names()


# Shared code that reads the registry instead of naming families.
SHARED = (
    "pipeline.py",
    "train_agent.py",
    "evaluate.py",
    "ncap.py",
    "artifacts.py",
    "banks.py",
    "registry.py",
    *(f"config/{p.name}" for p in sorted((ROOT / "worldmodel/config").glob("*.py"))),  # the schema included
)


def family_names_in(path: Path, names: set[str]) -> list[str]:
    """Where ``path``'s code names a family: an identifier, or a string literal, that is a family's name
    (docstrings and comments may mention one)."""
    import io
    import tokenize

    found = []
    for tok in tokenize.generate_tokens(io.StringIO(path.read_text()).readline):
        text = tok.string
        if tok.type == tokenize.STRING and text[:1] in "\"'" and text.strip("\"'") in names and len(text) < 20:
            found.append(f"{path.name}:{tok.start[0]} {text}")
        elif tok.type == tokenize.NAME and text in names:
            found.append(f"{path.name}:{tok.start[0]} {text}")
    return found


@pytest.mark.parametrize("module", SHARED)
def test_shared_code_names_no_family(module):
    from worldmodel import registry

    assert not family_names_in(ROOT / "worldmodel" / module, set(registry.names()))


def test_the_family_check_sees_names_and_string_literals(tmp_path):
    src = tmp_path / "shared.py"
    src.write_text('"""Mentions chae in prose."""\nif family == "kim":\n    import chae\nx = f"{a}merola"\n')
    assert family_names_in(src, {"chae", "kim", "merola"}) == ['shared.py:2 "kim"', "shared.py:3 chae"]


CASTS = {"int", "float", "str", "bool"}


def _root(node):
    """The name an attribute, subscript or method-call chain starts from (``cfg`` in ``cfg.agent.get("x")``)."""
    while True:
        if isinstance(node, ast.Attribute | ast.Subscript):
            node = node.value
        elif isinstance(node, ast.Call):
            node = node.func
        else:
            return node.id if isinstance(node, ast.Name) else None


def config_casts_in(path: Path, root: Path) -> list[str]:
    """Casts of an untyped config value: ``int(cfg.x)``, or of a name bound to a part of ``cfg``
    (``c = cfg.evaluate.kim`` ... ``int(c.trials)``), anywhere in the module."""
    tree = ast.parse(path.read_text(), filename=str(path))
    aliases, grew = {"cfg"}, True
    while grew:
        grew = False
        for node in ast.walk(tree):
            if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
                if node.targets[0].id not in aliases and _root(node.value) in aliases:
                    aliases.add(node.targets[0].id)
                    grew = True
    return [
        f"{path.relative_to(root)}:{node.lineno}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id in CASTS
        and len(node.args) == 1
        and isinstance(node.args[0], ast.Attribute | ast.Subscript | ast.Call)
        and _root(node.args[0]) in aliases
    ]


def test_stages_read_the_typed_config_not_casts_of_the_untyped_one():
    """``validate(cfg)`` returns the typed config; at most 10 casts of untyped values are left in worldmodel/."""
    casts = [c for path in sorted((ROOT / "worldmodel").rglob("*.py")) for c in config_casts_in(path, ROOT)]
    assert len(casts) <= 10, f"{len(casts)} casts of untyped config values:\n" + "\n".join(casts)


def test_the_cast_count_sees_aliases_and_method_calls(tmp_path):
    src = tmp_path / "m.py"
    src.write_text(
        "def f(cfg, n):\n    c = cfg.evaluate.kim\n    return int(c.trials), float(cfg.get('x')), int(n.k)\n"
    )
    assert [c.split(":")[1] for c in config_casts_in(src, tmp_path)] == ["3", "3"]  # c.trials, cfg.get; not n.k


def test_the_tests_readme_names_every_test_file():
    """tests/README.md's table says what each test file holds; a new file is listed there too."""
    listed = (ROOT / "tests/README.md").read_text()
    missing = [p.name for p in sorted((ROOT / "tests").glob("test_*.py")) if f"`{p.name}`" not in listed]
    assert missing == [], f"add {', '.join(missing)} to the table in tests/README.md"


MAX_MODULE_LINES, MAX_FUNCTION_LINES = 600, 80  # a module or a function longer than these is split


def oversized(paths) -> list[str]:
    """Modules over MAX_MODULE_LINES lines and functions (methods included, docstring and all) over
    MAX_FUNCTION_LINES."""
    found = []
    for path in paths:
        text = path.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            found.append(f"{path.relative_to(ROOT)}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text, filename=str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {length} lines")
    return found


def test_no_module_or_function_of_the_pipeline_or_the_simulator_is_oversized():
    paths = sorted([*(ROOT / "worldmodel").rglob("*.py"), *(ROOT / "envs").rglob("*.py")])
    assert not oversized(paths)


def test_the_size_check_finds_a_long_function(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    src = tmp_path / "long.py"
    src.write_text("def f():\n" + "    x = 1\n" * (MAX_FUNCTION_LINES - 1))
    assert oversized([src]) == []  # exactly at the limit
    src.write_text("def f():\n" + "    x = 1\n" * MAX_FUNCTION_LINES)
    assert oversized([src]) == ["long.py:1 f: 81 lines"]
