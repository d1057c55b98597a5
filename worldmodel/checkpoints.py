"""Reading checkpoints without running anything they carry (docs/design.md §9, "What a checkpoint may hold").

A checkpoint is a pickle, and a pickle can name any function to call while it is read. Every checkpoint here is
therefore read by torch's weights-only unpickler, which builds tensors, plain data (dicts, lists, tuples, strings,
numbers, None) and the few types in ``ALLOWED`` and refuses any other name unread. What the project's checkpoints
hold besides tensors and plain data is numpy's arrays, dtypes and scalars (replay buffers, numpy's RNG state), so
``ALLOWED`` is those. A file naming anything else is refused with a ``StageError`` naming the file and the names.

A run folder from elsewhere is then as safe to load as its tensors: its digests in ``provenance.json`` vouch for
nothing, since whoever hands over the folder hands over those too.

    python -m worldmodel.checkpoints check PATH...                   # which checkpoints read safely, which not
    python -m worldmodel.checkpoints trust PATH --allow MODULE.NAME  # rewrite a checkpoint you trust as safe data

``trust`` is the one place where a name outside ``ALLOWED`` is built, and only the names it is given: it reads the
file with those allowed too, writes the content back as the project writes checkpoints, checks that the new file
reads safely, and records its new digest where its run recorded the old one. What was built on it sees a new input
and is rebuilt by the pipeline.
"""

from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path
from typing import Any

from .common import StageError

# numpy as pickled by numpy 2: an array is _reconstruct(ndarray, ...) then its state, a dtype is dtype(...) then its
# state, a scalar is scalar(dtype, bytes); and pickle's protocol 2 writes an empty bytes object as bytes(). None of
# them calls anything a file names.
ALLOWED = (
    "builtins.bytes",
    "numpy._core.multiarray._reconstruct",
    "numpy._core.multiarray.scalar",
    "numpy.ndarray",
    "numpy.dtype",
)
# The dtypes whose state a file may set: booleans and numbers. An object array, whose items could be anything, is
# refused.
NUMERIC_DTYPES = "?bBhHiIlLqQefdFD"


def _allowed(also_allow: tuple[str, ...]) -> list:
    import numpy as np

    # by name as well as by object: an older numpy's name for the same function (numpy.core...) is another name
    named = [(_resolve(name), name) for name in (*ALLOWED, *also_allow)]
    return named + [type(np.dtype(c)) for c in NUMERIC_DTYPES]


def _resolve(name: str):
    import importlib

    module, _, attr = name.rpartition(".")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError, ValueError) as err:
        raise StageError(f"--allow {name}: there is no such name to allow ({err})") from None


def named_globals(path: Path) -> list[str]:
    """The module-level names ``path``'s pickle would look up, outside torch's own safe set; read without
    unpickling (a scan of its opcodes)."""
    import torch

    return torch.serialization.get_unsafe_globals_in_checkpoint(str(path))


def foreign_names(path: Path) -> list[str]:
    """The names in ``path`` that neither torch nor ``ALLOWED`` builds: what makes it unsafe to read. Empty for a
    file that is not torch's zip format (which the project has always written), whose names cannot be listed."""
    try:
        return [name for name in named_globals(path) if name not in ALLOWED]
    except ValueError:
        return []


def read_checkpoint(path: Path, also_allow: tuple[str, ...] = ()) -> Any:
    """``path`` unpickled by torch's weights-only loader with ``ALLOWED`` (and ``also_allow``, which only ``trust``
    passes) on the CPU. A file naming anything else is a StageError that names the file and the names, and nothing
    in it is built."""
    import torch

    try:
        with torch.serialization.safe_globals(_allowed(also_allow)):
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        foreign = [name for name in foreign_names(path) if name not in also_allow]
        if foreign:
            raise StageError(refusal(path, foreign)) from None
        # a type built from an allowed name (a dtype other than a number's); else the file is damaged, not unsafe
        lines = str(err).splitlines()
        detail = next((line.split("but got ")[-1] for line in lines if "but got " in line), None)
        if detail is None:
            raise
        raise StageError(
            f"{path} was refused unread: it holds {detail.strip()}, which no checkpoint of this project holds. Delete "
            f"{Path(path).parent} and rerun the stage that wrote it."
        ) from None


def refusal(path: Path, foreign: list[str]) -> str:
    return (
        f"{path} was refused unread: it names {', '.join(foreign)}, which no checkpoint of this project holds, and "
        "reading it could run code. A run folder from someone else: do not use it. A run of your own, written by "
        f"an older version: delete {Path(path).parent} and rerun the stage that wrote it, or, if you trust the file, "
        f"`python -m worldmodel.checkpoints trust {path} {' '.join('--allow ' + n for n in foreign)}` rewrites it "
        "as plain data."
    )


def trust(path: Path, allow: list[str]) -> str:
    """Rewrite ``path``, read with ``allow`` added to ``ALLOWED``, as the project writes checkpoints; refuse when
    the rewritten file still does not read safely (the names build objects, not plain data). Returns what was
    done."""
    from . import artifacts
    from .common import atomic_torch_save, file_sha256

    try:
        read_checkpoint(path)
        return f"{path} already reads safely; left as it is"
    except StageError:
        pass  # refused: what it names decides whether trust can help
    except Exception as err:  # damaged, not unsafe
        raise StageError(f"{path} cannot be read ({type(err).__name__}); trusting it would not help") from None
    unlisted = [name for name in foreign_names(path) if name not in allow]
    if unlisted:
        raise StageError(f"{path} also names {', '.join(unlisted)}; trust it by name with --allow too, or not at all")
    state = read_checkpoint(path, tuple(allow))  # still refused when what it holds is no name: a date, an object
    record = artifacts.read_provenance(path.parent) or {}
    before = file_sha256(path)
    tmp = path.with_name(path.name + ".trusted")
    atomic_torch_save(state, tmp)
    still = foreign_names(tmp)
    if still:
        tmp.unlink()
        raise StageError(
            f"{path} holds objects of {', '.join(still)}, not plain data: rewritten, it would still be refused. Delete "
            f"{path.parent} and rerun the stage that wrote it."
        )
    tmp.replace(path)
    after = file_sha256(path)
    outputs = record.get("outputs") or {}
    if outputs.get(path.name) == before:
        artifacts.write_provenance(path.parent, {**record, "outputs": {**outputs, path.name: after}})
    return (
        f"{path} rewritten as plain data, trusting {', '.join(allow)} (SHA-256 {before[:12]} -> {after[:12]}); "
        "what was built on it sees a new input and is rebuilt by the pipeline"
    )


def check(paths: list[Path]) -> int:
    """Print, for each checkpoint under ``paths``, whether it reads safely (reading it is safe: nothing outside
    ``ALLOWED`` is built); 2 when any does not."""
    files = [f for p in paths for f in ([p] if p.is_file() else sorted(p.rglob("*.pt")))]
    refused = 0
    for f in files:
        try:
            read_checkpoint(f)
            print(f"{f}: reads safely")
        except Exception as err:  # refused, or damaged
            refused += 1
            print(f"{f}: REFUSED. {err if isinstance(err, StageError) else f'cannot be read ({type(err).__name__})'}")
    print(f"{len(files)} checkpoint(s), {refused} refused")
    return 2 if refused else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m worldmodel.checkpoints", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("check", help="say whether each checkpoint under PATH reads safely").add_argument(
        "paths", nargs="+", type=Path
    )
    t = sub.add_parser("trust", help="rewrite a checkpoint you trust, allowing the names given")
    t.add_argument("path", type=Path)
    t.add_argument("--allow", action="append", required=True, metavar="MODULE.NAME")
    args = parser.parse_args(argv)
    try:
        missing = [p for p in (args.paths if args.command == "check" else [args.path]) if not p.exists()]
        if missing:
            raise StageError(f"{', '.join(map(str, missing))}: no such file or folder")
        if args.command == "check":
            return check(args.paths)
        print(trust(args.path, args.allow))
        return 0
    except StageError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
