"""Every public module, class and function of the package has a docstring, and no docstring keeps a
timing history (measurements belong in docs/performance.md, where their runs are named).

Public: a module whose file name has no leading underscore, and in it every top-level function and
class, and every method of such a class, whose name has no leading underscore. Read from the source
(no imports), so Warp kernels and functions count like any other function."""

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOTS = [REPO / "evsemmap_warp", REPO / "kernels", REPO / "configs"]

# Being rewritten in parallel with the docstring work of issue 28: their docstrings are finished with
# that rewrite. Remove a file from this set once it passes; the test fails when a listed file is gone.
PENDING: set[str] = set()

# A timing change told as history ("took 82 ms against 5 ms", "2.5 s -> 0.6 s", "~1.5x as long"), or a
# measured rate ("0.5 M voxels/s", "12 GB/s", "3 M/s", "20 scans/s"): a number, an optional unit prefix,
# then bytes, a plural count or the prefix alone, per second. A unit with no number ("speed (m/s)") and
# physical rates ("1 m/s", "0.5 rad/s") are not measurements and do not match.
TIMING_HISTORY = re.compile(
    r"\d[\d.,]*\s?(?:ms|ns|µs|us|s)\b[^.;]{0,40}?(?:->|→|against|instead of)\s*~?\d"
    r"|\d(?:\.\d+)?x (?:as long|slower|faster|the time)"
    r"|took ~?\d[\d.,]*\s?(?:ms|ns|µs|us|s)\b"
    r"|\d[\d.,]*\s?(?:[kKMGT]i?\s?)?(?:B|[A-Za-z]*[a-z]s|[kKMGT])/s\b")


def _public_definitions(tree: ast.Module):
    def walk(body, prefix):
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and not node.name.startswith("_"):
                yield prefix + node.name, node
                if isinstance(node, ast.ClassDef):
                    yield from walk(node.body, prefix + node.name + ".")

    yield from walk(tree.body, "")


def _modules():
    for root in ROOTS:
        for path in sorted(root.rglob("*.py")):
            if path.name.startswith("_") and path.name != "__init__.py":
                continue
            yield path.relative_to(REPO).as_posix(), path


def test_every_public_name_has_a_docstring():
    missing = []
    for name, path in _modules():
        if name in PENDING:
            continue
        tree = ast.parse(path.read_text())
        if not ast.get_docstring(tree):
            missing.append(f"{name} (the module)")
        missing += [f"{name}: {qualname}" for qualname, node in _public_definitions(tree) if not ast.get_docstring(node)]
    assert not missing, f"{len(missing)} public names without a docstring:\n" + "\n".join(missing)


def test_the_pending_files_still_exist():
    gone = sorted(name for name in PENDING if not (REPO / name).exists())
    assert not gone, f"remove from PENDING: {gone}"


def test_no_docstring_keeps_a_timing_history():
    found = []
    for name, path in _modules():
        tree = ast.parse(path.read_text())
        for qualname, node in [("(the module)", tree), *_public_definitions(tree),
                               *((n.name, n) for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.ClassDef)))]:
            doc = ast.get_docstring(node) or ""
            match = TIMING_HISTORY.search(doc)
            if match and name not in PENDING:
                found.append(f"{name}: {qualname}: {match.group(0)!r}")
    assert not found, "timing history in docstrings (move it to docs/performance.md):\n" + "\n".join(sorted(set(found)))
