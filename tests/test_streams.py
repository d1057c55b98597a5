"""The random streams' tags live in one registry, ``envs/streams.py``, and nowhere else.

A stream is ``np.random.default_rng([seed, TAG, index...])``. Two checks:

* the registry: every tag names one stream, except the shared values listed in ``SHARED`` (each safe because
  another component of the two streams' seeds differs, see there), and it imports nothing.
* the source (``envs/``, ``worldmodel/``, ``experiments/``, read with ``ast`` so a call inside a function cannot
  hide): no integer literal stands as an element of a ``default_rng([...])`` / ``SeedSequence([...])`` list (or
  tuple), or as a stream argument of the kim peer's ``training_scenario(cfg, *stream)``, and no integer literal is
  added to a seed in ``manual_seed(seed + N)``. The rule admits no literal at all: every fixed number in those
  places is a tag and belongs in the registry. What stays in the code is a name or a computed index (an episode, a
  round, an epoch and batch, ``k`` of ``enumerate``, Scenario 1's ``int(round(ttc * 100))``); a multiplier that
  spreads a seed over epochs (``seed * 1000 + epoch``) is arithmetic, not a tag. A plain seed
  (``default_rng(seed)``, ``default_rng(0)``) is not a list and is not checked.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import numpy as np

from envs import streams

ROOT = Path(__file__).resolve().parent.parent
SCANNED = ("envs", "worldmodel", "experiments")
SEEDERS = {"default_rng", "SeedSequence"}

# value -> the streams allowed to share it, and why each pair is kept apart by another component of its seed
SHARED = {
    # [scenario seed, 2020] in the simulator vs [run seed, 2020, episode]: a scenario's own seed vs the run's seed
    2020: {"KIM_NEUTRAL_CARS", "KIM_TRAINING_EPISODES"},
    # [scenario seed, 2022] vs [run seed, 2022, episode] (a merola run) and [run seed, 2022, round, e] (a kim run):
    # the scenario's seed vs the run's, and the two run-seed streams belong to different families' runs
    2022: {"MEROLA_JUNCTION_DISTANCE", "MEROLA_TRAINING_EPISODES", "KIM_DAGGER_SCENARIOS"},
    # [run seed, 77] (padded to [run seed, 77, 0, 0]) vs [run seed, epoch, batch, 77]: the fourth words differ
    77: {"CHOOSER_MINIBATCHES", "RNN_OPEN_LOOP_START"},
    # [bank seed, k, 1] with k < 3 vs [label seed, 7779, r, e, 1]: the second words differ
    1: {"KIM_BANK_CROSSING", "KIM_COUNTERFACTUAL_PROPOSALS"},
}


def registry() -> dict[str, int]:
    return {name: value for name, value in vars(streams).items() if name.isupper() and isinstance(value, int)}


def test_every_stream_has_its_own_tag_except_the_listed_shares():
    tags = registry()
    assert len(tags) >= 20, sorted(tags)  # the registry is read at all
    assert all(not isinstance(v, bool) and v >= 0 for v in tags.values()), tags  # SeedSequence takes ints >= 0
    by_value = defaultdict(set)
    for name, value in tags.items():
        by_value[value].add(name)
    shared = {value: names for value, names in by_value.items() if len(names) > 1}
    assert shared == SHARED, "a new stream needs a value of its own; a deliberate share is listed in SHARED"


def test_the_kim_peers_training_streams_are_distinct():
    """``training_scenario(cfg, TAG, ...)`` draws every one of these from the same run seed and the same sampler."""
    kim = [
        streams.KIM_TRAINING_EPISODES,
        streams.KIM_DEMO_SCENARIOS,
        streams.KIM_DAGGER_SCENARIOS,
        streams.KIM_STUDENT_SCENARIOS,
        streams.KIM_CHOOSER_LABELS,
    ]
    assert len(set(kim)) == len(kim)


def test_a_shorter_seed_list_is_the_same_as_one_padded_with_zeros():
    """Why the registry's docstring warns that length alone does not separate streams (numpy's SeedSequence)."""
    draw = [np.random.default_rng(key).integers(2**31) for key in ([5, 2020], [5, 2020, 0], [5, 2020, 0, 0])]
    assert draw[0] == draw[1] == draw[2]


def test_the_registry_imports_nothing():
    """envs/ never imports torch, and worldmodel/ and experiments/ import the registry: it stays a list of numbers."""
    tree = ast.parse((ROOT / "envs" / "streams.py").read_text())
    imports = [n for n in ast.walk(tree) if isinstance(n, ast.Import | ast.ImportFrom)]
    assert all(isinstance(n, ast.ImportFrom) and n.module == "__future__" for n in imports)


def _name(func: ast.expr) -> str:
    return func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""


def _int_literal(node: ast.expr) -> int | None:
    """The integer a seed component spells out: ``7``, ``-7`` or ``int(7)``; None for anything computed."""
    if isinstance(node, ast.Call) and _name(node.func) == "int" and len(node.args) == 1:
        node = node.args[0]
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        node = node.operand
    if isinstance(node, ast.Constant) and isinstance(node.value, int) and not isinstance(node.value, bool):
        return node.value
    return None


def literal_tags(path: Path) -> list[tuple[int, str]]:
    """(line, source) of every seed in ``path`` spelling a tag as an integer literal (the module docstring's rule)."""
    text = path.read_text()
    found = []
    for node in ast.walk(ast.parse(text, filename=str(path))):
        if not isinstance(node, ast.Call):
            continue
        name = _name(node.func)
        parts: list[ast.expr] = []
        if name in SEEDERS:
            seeds = [*node.args[:1], *(k.value for k in node.keywords if k.arg in ("seed", "entropy"))]
            parts = [e for s in seeds if isinstance(s, ast.List | ast.Tuple) for e in s.elts]
        elif name == "training_scenario":
            parts = node.args[1:]
        elif name == "manual_seed":
            parts = [
                side
                for a in node.args
                if isinstance(a, ast.BinOp) and isinstance(a.op, ast.Add | ast.Sub)
                for side in (a.left, a.right)
            ]
        if any(_int_literal(p) is not None for p in parts):
            found.append((node.lineno, ast.get_source_segment(text, node)))
    return found


def test_no_stream_tag_is_a_literal_in_the_source():
    offenders = {
        f"{path.relative_to(ROOT)}:{line}": src
        for folder in SCANNED
        for path in sorted((ROOT / folder).rglob("*.py"))
        for line, src in literal_tags(path)
    }
    assert not offenders, f"name these tags in envs/streams.py and import them: {offenders}"


def test_the_check_sees_literal_tags_in_every_spelling(tmp_path):
    """The check itself can fail: each literal tag below is found, inside a function or not, and the named or
    computed components beside them are not."""
    bad = tmp_path / "fake_stage.py"
    bad.write_text(
        "import numpy as np\n"
        "rng = np.random.default_rng([seed, 4242, episode])\n"
        "def draw(seed, k):\n"
        "    a = np.random.SeedSequence((seed, k, 1))\n"
        "    b = default_rng(seed=[int(seed), int(77)])\n"
        "    c = kim.training_scenario(cfg, 2021, k)\n"
        "    d = torch.Generator().manual_seed(seed + 99)\n"
        "    return a, b, c, d\n"
    )
    assert [line for line, _ in literal_tags(bad)] == [2, 4, 5, 6, 7]
    good = tmp_path / "fake_clean.py"
    good.write_text(
        "import numpy as np\n"
        "from envs.streams import AGENT_FOCUS_EPISODES\n"
        "def draw(seed, episode, ttc, epoch):\n"
        "    a = np.random.default_rng([seed, AGENT_FOCUS_EPISODES, episode])\n"
        "    b = np.random.default_rng([seed, int(round(ttc * 100))])\n"
        "    c = np.random.default_rng(0)\n"
        "    d = torch.Generator().manual_seed(int(seed) * 1000 + epoch)\n"
        "    return a, b, c, d\n"
    )
    assert literal_tags(good) == []
