"""Speed figures on record: the rule that ties every measured speed in README.md and docs/ to a run
record, the check of that rule, and the tables generated from records.

The rule. A *speed figure* is a number with a time unit (s, ms, µs, ns, min, seconds, minutes) or a
rate unit (anything "/s" or "per second": points/s, M voxel updates/s, GB/s) in prose or in a table
cell, and every number past the first column of a *performance table* (a table whose header names a
time, a rate or a comparison: "s", "wall", "time", "/s", "vs", "×", "roofline", ...), ratios (×3.8,
0.93x) and shares (12 %) included. Text in code (fenced blocks, `inline code`) and link targets is not read. Every block of
text (a paragraph, a list, a table: lines up to a blank line) that holds a speed figure must say
where it comes from, in an HTML comment on the line before it:

* ``<!-- record: docs/bench/NAME.json -->`` (or ``docs/cpp_side_by_side.json``): every figure of the
  block must be a number of that record's JSON, at the precision printed: 9.29 M matches
  9,291,234 (the unit's scale: k, M, G, ms, µs, ns, min, %, MB, GB), 0.9 s matches 0.89;
* ``<!-- record: none (WHY; rerun TOOL) -->``: measured before records were kept; the check lists
  these blocks, and the pages' test refuses them (a figure there is rerun for a record, or dropped);
* ``<!-- record: n/a (WHY) -->``: the numbers only look like speeds (a setting's default, a stamp);
* ``<!-- page-record: ... -->`` (anywhere in a file): the same for every block of the file that has no
  marker of its own (a page a tool writes whole, as tools/kernel_study.py writes docs/kernel_study.md).

A marker may end with ``; table: TOOL``: the block is a table this script generates from a record of
TOOL (``table``, below), and regenerating it replaces the block and the marker.

    python tools/perf_records.py check                       # README.md and docs/: problems, unrecorded blocks
    python tools/perf_records.py table docs/bench/bench_integrate-<UTC>.json [--doc docs/performance.md]
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
NONE = "none"
NOT_MEASURED = "n/a"

MARKER = re.compile(r"<!--\s*(?P<page>page-)?record:\s*(?P<target>.*?)(?:\s*;\s*table:\s*(?P<table>[\w-]+))?\s*-->")
FENCE = re.compile(r"^\s*(```|~~~)")
# A number: not part of a word or of another number; digits grouped by commas or not, an optional fraction.
NUMBER = r"(?<![\w.,^])(?P<num>\d{1,3}(?:,\d{3})+(?:\.\d+)?|\d+(?:\.\d+)?)"
TIME_UNITS = {"ns": 1e-9, "µs": 1e-6, "μs": 1e-6, "us": 1e-6, "ms": 1e-3, "s": 1.0, "sec": 1.0, "second": 1.0, "seconds": 1.0,
              "min": 60.0, "minute": 60.0, "minutes": 60.0, "hours": 3600.0}
MULTIPLIERS = {"k": 1e3, "M": 1e6, "G": 1e9}
BYTE_UNITS = {"KB": (1e3, 2**10), "MB": (1e6, 2**20), "GB": (1e9, 2**30)}
# Joined to the number that carries the unit ("1.9 and 2.4 s", "41 -> 14 ns", "0.20-0.22 s").
JOINER = r"(?:\s*(?:,|and|or|to|/|->|→|against|-|–)\s*)"
TIME = re.compile(NUMBER + r"(?P<rest>(?:" + JOINER + r"\d[\d,.]*)*)\s?(?P<unit>" + "|".join(sorted(TIME_UNITS, key=len, reverse=True))
                  + r")(?![\w/])")
RATE = re.compile(NUMBER + r"(?P<rest>(?:" + JOINER + r"\d[\d,.]*)*)\s?(?:(?P<mult>[kMG])\s)?(?P<unit>(?:[A-Za-z][\w-]*\s){0,2}[A-Za-z][\w-]*/s"
                  r"|(?:[A-Za-z][\w-]*\s){0,2}per second)(?!\w)")
# A table cell's number: also right after an "x" (x1.23), with its multiplier and unit.
CELL_NUMBER = re.compile(r"(?:(?<=x)|(?<![\w.,^]))(?P<num>\d{1,3}(?:,\d{3})+(?:\.\d+)?|\d+(?:\.\d+)?)(?!\d)"
                         r"(?:\s?(?P<mult>[kMG])(?!\w))?(?P<unit>\s?(?:%|x|×|ms|µs|ns|s|MB|GB|KB)(?!\w))?")
# A speed ratio in prose, with its decimals: "x0.906", "×12.3" (not "×100", a scale, nor "x86-64").
RATIO = re.compile(r"(?<![\w.])[x×](?P<num>\d+\.\d+)(?![\w.-])")
PERFORMANCE_HEADER = re.compile(r"(^|[\s(])(s|ms|wall|time|seconds|speed|throughput|speed-up)([\s)]|$)|/s\b|\bvs\b|×|ratio|roofline",
                                re.IGNORECASE)


@dataclass
class Figure:
    """A number a block claims: its text, its value, its decimals and the scales its unit allows."""

    text: str
    value: float
    decimals: int
    scales: tuple[float, ...] = (1.0,)


@dataclass
class Block:
    """Lines start..end (1-based) of a file, the marker that covers them and the figures they hold."""

    path: Path
    start: int
    end: int
    lines: list[str]
    target: str | None = None  # a record path, "none (...)" or None (no marker)
    table: str | None = None
    marker_line: int | None = None
    figures: list[Figure] = field(default_factory=list)


def _plain(text: str) -> str:
    """The text without inline code, link targets and HTML comments."""
    text = re.sub(r"<!--.*?-->", " ", text)
    text = re.sub(r"`[^`]*`", " ", text)
    return re.sub(r"\]\([^)]*\)", "]", text)


def _figure(text: str, scales=(1.0,)) -> Figure:
    digits = text.replace(",", "")
    decimals = len(digits.split(".")[1]) if "." in digits else 0
    return Figure(text, float(digits), decimals, tuple(scales))


def _unit_scales(unit: str, mult: str | None) -> tuple[float, ...]:
    scales = {1.0}
    if mult:
        scales.add(MULTIPLIERS[mult])
    word = unit.split("/")[0].split()[-1] if unit.strip() else ""
    if word in TIME_UNITS:
        scales.add(TIME_UNITS[word])
    if word in BYTE_UNITS:
        scales.update(BYTE_UNITS[word])
    if word == "%":
        scales.add(0.01)
    return tuple(sorted(scales))


def prose_figures(line: str) -> list[Figure]:
    """The speed figures of prose: numbers with a time or rate unit (and the numbers joined to them)."""
    text = _plain(line)
    out = []
    for pattern in (TIME, RATE):
        for match in pattern.finditer(text):
            scales = _unit_scales(match["unit"], match.groupdict().get("mult"))
            numbers = [match["num"]] + re.findall(r"\d[\d,]*(?:\.\d+)?", match["rest"] or "")
            out += [_figure(n.rstrip(",."), scales) for n in numbers if n.rstrip(",.")]
    out += [_figure(match["num"]) for match in RATIO.finditer(text)]
    return out


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def table_figures(lines: list[str]) -> list[Figure]:
    """Every number past the first column of a performance table's body (with its unit's scales)."""
    out = []
    for line in lines[2:]:
        for cell in _cells(line)[1:]:
            for match in CELL_NUMBER.finditer(_plain(cell)):
                out.append(_figure(match["num"], _unit_scales((match["unit"] or "").strip(), match["mult"])))
    return out


def is_performance_table(lines: list[str]) -> bool:
    return (len(lines) >= 2 and lines[0].lstrip().startswith("|") and set(lines[1].replace("|", "").strip()) <= set("-: ")
            and any(PERFORMANCE_HEADER.search(_plain(cell)) for cell in _cells(lines[0])))


def blocks(path: Path) -> list[Block]:
    """The file's blocks of text outside code, each with the marker that covers it and its speed figures."""
    lines = path.read_text().splitlines()
    page_target = None
    for line in lines:
        match = MARKER.search(line)
        if match and match["page"]:
            page_target = match["target"]
    out, current, pending, in_code = [], None, None, False
    for number, line in enumerate(lines, start=1):
        if FENCE.match(line):
            in_code = not in_code
            current = None
            continue
        if in_code:
            continue
        match = MARKER.search(line)
        if match and not match["page"] and line.strip().startswith("<!--"):
            pending = (match["target"], match["table"], number)
            current = None
            continue
        if not line.strip():
            current = None
            continue
        if current is None:
            target, table, marker_line = pending if pending else (None, None, None)
            current = Block(path, number, number, [], target, table, marker_line)
            pending = None
            out.append(current)
        current.lines.append(line)
        current.end = number
    for block in out:
        if is_performance_table(block.lines):
            block.figures = table_figures(block.lines) + [f for line in block.lines[2:] for f in prose_figures(_cells(line)[0])]
        else:  # whole, so that code spans across lines are left out
            block.figures = prose_figures("\n".join(block.lines))
        if block.target is None and block.figures and page_target is not None:
            block.target = page_target
    return out


def record_numbers(path: Path) -> list[float]:
    """Every number of a record's JSON (numbers inside its strings are not read)."""
    values = []

    def walk(node):
        if isinstance(node, bool):
            return
        if isinstance(node, (int, float)) and math.isfinite(node):
            values.append(float(node))
        elif isinstance(node, dict):
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(json.loads(path.read_text()))
    return values


def traceable(figure: Figure, values: list[float]) -> bool:
    """Whether some record number, in one of the figure's scales, prints as the figure (half a unit of its
    last digit either way)."""
    tolerance = 0.5 * 10.0 ** -figure.decimals
    for scale in figure.scales:
        for value in values:
            if abs(abs(value) / scale - figure.value) <= tolerance * (1 + 1e-9) + 1e-12:
                return True
    return False


@dataclass
class Report:
    problems: list[str] = field(default_factory=list)
    unrecorded: list[Block] = field(default_factory=list)  # marked "none": measured before records
    not_measured: list[Block] = field(default_factory=list)  # marked "n/a"


def documents(repo: Path = REPO) -> list[Path]:
    """README.md and every page under docs/."""
    return [repo / "README.md"] + sorted((repo / "docs").rglob("*.md"))


def check(paths: list[Path], repo: Path = REPO) -> Report:
    """Apply the rule to ``paths``: a problem for every block of speed figures without a marker, every
    marker naming a record that is not there, every figure its record does not hold."""
    report = Report()
    cache: dict[Path, list[float]] = {}
    for path in paths:
        for block in blocks(path):
            if not block.figures:
                continue
            where = f"{path.relative_to(repo) if path.is_relative_to(repo) else path}:{block.start}"
            if block.target is None:
                report.problems.append(f"{where}: speed figures ({', '.join(f.text for f in block.figures[:4])}) with no "
                                       "<!-- record: ... --> marker naming where they come from")
                continue
            name = block.target.split()[0] if block.target.split() else ""
            if name.lower() == NONE:
                report.unrecorded.append(block)
                continue
            if name.lower() == NOT_MEASURED:
                report.not_measured.append(block)
                continue
            record = Path(name) if Path(name).is_absolute() else repo / name
            if not name or not record.is_file():
                report.problems.append(f"{where}: the marker names {name or 'no record'}, which is not there")
                continue
            if record not in cache:
                cache[record] = record_numbers(record)
            missing = [f.text for f in block.figures if not traceable(f, cache[record])]
            if missing:
                report.problems.append(f"{where}: not in {name}: {', '.join(missing)}")
    return report


# ---------------------------------------------------------------------------- tables generated from records
def _three_digits(value: float) -> str:
    """Three significant digits, trailing zeros kept (1.20, 39.5, 259)."""
    decimals = max(0, 2 - math.floor(math.log10(abs(value)))) if value else 2
    return f"{value:.{decimals}f}"


def _rate(value: float) -> str:
    for scale, suffix in ((1e9, " G"), (1e6, " M"), (1e3, " k")):
        if value >= scale:
            return _three_digits(value / scale) + suffix
    return _three_digits(value)


def bench_integrate_table(record: dict) -> str:
    """The integration table of docs/performance.md from a tools/bench_integrate.py record."""
    results = record["results"]
    rows = results["rows"]
    lines = ["| row | input pts/s | voxel updates/s | cells | shard merge + summary (s) | vs vectorised numpy (1 thread) "
             "| vs original C++ (timed when the caption says) |", "|---|---|---|---|---|---|---|"]

    def vs_cpp(row: dict) -> str:
        if row.get("vs_cpp") is None:
            return "–"
        if row.get("cpp_semantics") == "other":  # the release's rate beside the clean ebs, for scale
            return f"×{row['vs_cpp']:.1f} vs EvSemMap EBS {row['cpp_points_per_s'] / 1e3:.0f} k ({row['cpp_threads']}), other map semantics"
        return f"×{row['vs_cpp']:.1f} vs {row['cpp_points_per_s'] / 1e3:.0f} k ({row['cpp_threads']})"

    for name in results["methods"]:
        row = rows[name]
        lines.append(f"| `{name}`, RELLIS-3D preset ({row['workers']} threads) | {_rate(row['input_points_per_s'])} | "
                     f"{_rate(row['voxel_updates_per_s'])} | {row['voxels']:,} | {row['summary_seconds']:.3f} | "
                     f"{'×%.1f' % row['vs_numpy'] if 'vs_numpy' in row else '–'} | {vs_cpp(row)} |")
    for name in results["like_for_like"]:
        per_thread = [(threads, rows[f"{name}@{threads}t"]) for threads in results["thread_counts"] if f"{name}@{threads}t" in rows]
        label = f"`s-bki`, sbki mode, free_res {name.split('@fr')[1]}" if name.startswith("s-bki-compat@fr") else f"`{name}`"
        threads = " / ".join(str(t) for t, _ in per_thread)
        joined = lambda fmt: " / ".join(fmt(row) for _, row in per_thread)  # noqa: E731
        cells = sorted({row["voxels"] for _, row in per_thread})
        lines.append(f"| {label}, {threads} thread{'s' if threads != '1' else ''} | {joined(lambda r: _rate(r['input_points_per_s']))} | "
                     f"{joined(lambda r: _rate(r['voxel_updates_per_s']))} | {' / '.join(f'{c:,}' for c in cells)} | "
                     f"{joined(lambda r: '%.3f' % r['summary_seconds'])} | – | {joined(vs_cpp)} |")
    return "\n".join(lines)


def bench_integrate_caption(record: dict, record_path: str) -> str:
    results = record["results"]
    machine = record.get("machine", {})
    command = " ".join(str(part) for part in record.get("command", []))
    name = Path(record_path).name
    return (f"*From [`{name}`](bench/{name}): `{command}` at commit `{str(record.get('commit', ''))[:10]}`"
            f"{'' if record.get('tree_clean', True) else ' (modified tree)'}, {record.get('utc', '')}, {machine.get('cpu_model', '')} "
            f"({machine.get('cores', '')} cores), device {results['device']}, {results['workload']['scans']} of the workload's scans, median of "
            f"{results['repeats']} after a warm-up{_order_note(results)}; C++: {results['cpp']['summary']}{_cpp_day_note(record)}{_cpp_cpu_note(record)}.*")


def _order_note(results: dict) -> str:
    """How the run ordered its repeats, where its record says (records before the rounds do not)."""
    return " (the rows in rounds, one repeat of each per round)" if results.get("order", "").startswith("rounds") else ""


def _cpp_day_note(record: dict) -> str:
    """Said when the C++ figures were timed on another day than the run (a date in their summary): the ratios then
    compare two days' VMs of one machine kind, not two programs side by side."""
    cpp_day = re.search(r"\d{4}-\d{2}-\d{2}", record["results"]["cpp"]["summary"])
    run_day = str(record.get("utc", ""))[:10]
    if cpp_day is None or not run_day or cpp_day.group(0) == run_day:
        return ""
    return (f". The C++ was timed on {cpp_day.group(0)}, not beside this run ({run_day}): its ratios compare two days' VMs of one "
            "machine kind, not two programs side by side")


def _cpp_cpu_note(record: dict, repo: Path = REPO) -> str:
    """Whether the run's CPU model is the one the C++ figures were timed on (their file's ``measured.machine``):
    VMs of one machine kind have come with either of two CPU models, so a ratio may compare two CPUs too."""
    cpu = record.get("machine", {}).get("cpu_model", "")
    try:
        cpp_machine = json.loads((repo / record["results"]["cpp"]["file"]).read_text())["measured"]["machine"]
    except (OSError, KeyError, TypeError, ValueError):
        return ""
    if not cpu or not isinstance(cpp_machine, str):
        return ""
    if cpu in cpp_machine:
        return f"; this run's CPU model ({cpu}) is the one the C++ was timed on"
    return f"; the C++ was timed on another CPU model ({cpp_machine}) than this run's ({cpu}), so its ratios compare two CPUs as well"


TABLES = {"bench_integrate": (bench_integrate_table, bench_integrate_caption)}


def regenerate(doc: Path, record_path: Path, repo: Path = REPO) -> None:
    """Replace the table of ``doc`` marked ``table: TOOL`` (TOOL: the record's tool) with the table made
    from the record, under a marker naming the record, and its caption below it."""
    record = json.loads(record_path.read_text())
    tool = record["tool"]
    if tool not in TABLES:
        raise SystemExit(f"{record_path}: no table is generated from {tool} records (known: {', '.join(TABLES)})")
    make_table, make_caption = TABLES[tool]
    relative = record_path.resolve().relative_to(repo).as_posix() if record_path.resolve().is_relative_to(repo) else str(record_path)
    lines = doc.read_text().splitlines()
    marked = [b for b in blocks(doc) if b.table == tool]
    if len(marked) != 1:
        raise SystemExit(f"{doc}: expected one table marked 'table: {tool}', found {len(marked)}")
    table = marked[0]
    end = table.end
    after = [b for b in blocks(doc) if b.start > table.end]
    if after and after[0].table is None and after[0].marker_line is not None and f"caption: {tool}" in lines[after[0].marker_line - 1]:
        end = after[0].end  # the previous caption goes with its table
    new = [f"<!-- record: {relative}; table: {tool} -->", make_table(record), "",
           f"<!-- record: {relative} (caption: {tool}) -->", make_caption(record, relative)]
    lines[table.marker_line - 1:end] = "\n".join(new).splitlines()
    doc.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    check_parser = sub.add_parser("check", help="the rule over README.md and docs/ (or the files given)")
    check_parser.add_argument("files", nargs="*", type=Path)
    table_parser = sub.add_parser("table", help="regenerate the table a record's tool has in --doc")
    table_parser.add_argument("record", type=Path)
    table_parser.add_argument("--doc", type=Path, default=REPO / "docs" / "performance.md")
    args = parser.parse_args(argv)
    if args.command == "table":
        regenerate(args.doc, args.record)
        print(f"{args.doc}: table regenerated from {args.record}")
        return 0
    report = check([f.resolve() for f in args.files] or documents())
    for block in report.unrecorded:
        print(f"unrecorded: {block.path.relative_to(REPO) if block.path.is_relative_to(REPO) else block.path}:{block.start}: {block.target}")
    for problem in report.problems:
        print(f"PROBLEM: {problem}")
    return 1 if report.problems else 0


if __name__ == "__main__":
    sys.exit(main())
