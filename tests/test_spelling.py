"""One spelling: the code, its flags and its docs say center and color (the map file's schema says
centers), and the command line reads those spellings only."""

import re
import tokenize
from pathlib import Path

from evsemmap_warp.apps.cli import build_parser

from conftest import run_cli

REPO = Path(__file__).resolve().parents[1]
SOURCES = ["evsemmap_warp", "kernels", "configs", "tools", "examples", "tests", "docs", ".ci"]


def _files():
    for root in SOURCES:
        for path in sorted((REPO / root).rglob("*")):
            if path.is_file() and (path.suffix in (".py", ".md", ".yaml", ".yml") or path.name == "run"):
                yield path.relative_to(REPO).as_posix(), path
    yield "README.md", REPO / "README.md"


def test_identifiers_spell_center_and_color():
    found = []
    for name, path in _files():
        if path.suffix != ".py":
            continue
        with open(path, "rb") as f:
            found += [f"{name}:{tok.start[0]}: {tok.string}" for tok in tokenize.tokenize(f.readline)
                      if tok.type == tokenize.NAME and re.search(r"colour|centre", tok.string, re.I)]
    assert not found, "identifiers spelled colour/centre (the file schema says centers; use center and color):\n" + "\n".join(found)


def test_the_docs_spell_center_and_color():
    # the prose follows the identifiers: one spelling
    pages = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    found = [f"{path.relative_to(REPO)}:{number}: {line.strip()}" for path in pages
             for number, line in enumerate(path.read_text().split("\n"), 1) if re.search(r"colour|centre", line, re.I)]
    assert not found, "spell color and center, as the code does:\n" + "\n".join(found)


def test_the_command_line_reads_color_by_only(capsys):
    assert build_parser().parse_args(["project", "seq", "--out", "gt", "--color-by", "depth"]).color_by == "depth"
    line = run_cli(capsys, "project", "seq", "--out", "gt", "--colour-by", "depth")
    assert line == "evsemmap: error: unrecognized arguments: --colour-by depth (see evsemmap --help)"
