"""How easy the codebase is to hold, in counts: the map's entry points, the largest class and module, the
functions over 80 lines, private names used outside the module that defines them, and the run records under
docs/bench that the docs cite and do not cite.

    python tools/house_counts.py            # the table
    python tools/house_counts.py --json     # the same as JSON, with every name behind each count
    python tools/house_counts.py --repo DIR # another checkout (a git worktree of an older commit, say)

A private name counts as used across modules when a file imports ``_name`` from another module, or reads
``something._name`` where ``something`` is not ``self`` or ``cls``, the file defines no ``_name`` itself and
another file of the project does.
"""

from __future__ import annotations

import argparse
import ast
import json
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CODE_FOLDERS = ("evsemmap_warp", "kernels", "tools", "examples")
LONG_FUNCTION_LINES = 80


@dataclass
class Counts:
    map_entry_points: list[str] = field(default_factory=list)
    largest_class: dict = field(default_factory=dict)
    largest_module: dict = field(default_factory=dict)
    long_functions: list[str] = field(default_factory=list)
    private_names_across_modules: list[str] = field(default_factory=list)
    records_cited: list[str] = field(default_factory=list)
    records_not_cited: list[str] = field(default_factory=list)


def code_files(repo: Path) -> list[Path]:
    return sorted(p for folder in CODE_FOLDERS for p in (repo / folder).rglob("*.py") if "__pycache__" not in p.parts)


def _defined_names(tree: ast.AST) -> set[str]:
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
        elif isinstance(node, ast.arg):
            names.add(node.arg)
    return names


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_uses(path: Path, tree: ast.AST, repo: Path, project_names: set[str]) -> list[str]:
    """This file's uses of private names that another file of the project defines (``project_names``: every
    name the project's files define; os._exit and the like are the standard library's business)."""
    where = path.relative_to(repo).as_posix()
    defined = _defined_names(tree)
    uses = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            uses += [f"{where}:{node.lineno} imports {alias.name} from {node.module or '.'}"
                     for alias in node.names if _is_private(alias.name)]
        elif isinstance(node, ast.Attribute) and _is_private(node.attr) and node.attr not in defined \
                and node.attr in project_names:
            owner = node.value.id if isinstance(node.value, ast.Name) else None
            if owner not in ("self", "cls"):
                uses.append(f"{where}:{node.lineno} reads {ast.unparse(node.value)}.{node.attr}")
    return uses


def cited_records(repo: Path) -> tuple[list[str], list[str]]:
    records = sorted(p.name for p in (repo / "docs" / "bench").glob("*.json"))
    text = "\n".join(p.read_text() for p in [repo / "README.md", *sorted((repo / "docs").rglob("*.md"))])
    cited = [name for name in records if re.search(re.escape(name), text)]
    return cited, [name for name in records if name not in cited]


def count(repo: Path = REPO) -> Counts:
    counts = Counts()
    largest_class = (0, "", 0)
    trees = {path: ast.parse(path.read_text()) for path in code_files(repo)}
    project_names = set().union(*(_defined_names(tree) for tree in trees.values()))
    for path, tree in trees.items():
        where = path.relative_to(repo).as_posix()
        lines = len(path.read_text().splitlines())
        if lines > counts.largest_module.get("lines", 0):
            counts.largest_module = {"module": where, "lines": lines}
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                methods = [n for n in node.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
                size = node.end_lineno - node.lineno + 1
                if size > largest_class[0]:
                    largest_class = (size, f"{where}:{node.name}", len(methods))
                if where == "evsemmap_warp/core/voxel_map.py" and node.name == "VoxelMap":
                    counts.map_entry_points = [m.name for m in methods if not m.name.startswith("_")]
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                size = node.end_lineno - node.lineno + 1
                if size > LONG_FUNCTION_LINES:
                    counts.long_functions.append(f"{where}:{node.lineno} {node.name} ({size} lines)")
        counts.private_names_across_modules += private_uses(path, tree, repo, project_names)
    counts.largest_class = {"class": largest_class[1], "lines": largest_class[0], "methods": largest_class[2]}
    counts.records_cited, counts.records_not_cited = cited_records(repo)
    return counts


def table(counts: Counts) -> str:
    rows = [("entry points of the map (VoxelMap's public methods)", len(counts.map_entry_points)),
            ("largest class", f"{counts.largest_class['class']}: {counts.largest_class['lines']} lines, "
                              f"{counts.largest_class['methods']} methods"),
            ("largest module", f"{counts.largest_module['module']}: {counts.largest_module['lines']} lines"),
            (f"functions over {LONG_FUNCTION_LINES} lines", len(counts.long_functions)),
            ("private names used outside their module", len(counts.private_names_across_modules)),
            ("run records cited / not cited", f"{len(counts.records_cited)} / {len(counts.records_not_cited)}")]
    return "\n".join(f"| {name} | {value} |" for name, value in [("count", "value"), ("---", "---"), *rows])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repo", type=Path, default=REPO, help="the checkout to count (default: this one)")
    parser.add_argument("--json", action="store_true", help="JSON with every name behind each count")
    args = parser.parse_args(argv)
    counts = count(args.repo.resolve())
    print(json.dumps(asdict(counts), indent=1) if args.json else table(counts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
