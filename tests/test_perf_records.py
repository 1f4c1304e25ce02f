"""Speed figures on record: every measured speed in README.md and docs/ names the run record it comes from
and is in it (the rule: tools/perf_records.py), the integration table is generated from a record, and
the side-by-side record states both sides' compiler flags.

Blocks marked "none" (measured before the tools kept records) fail here: every figure of the pages comes
from a committed record, or is not a measurement ("n/a")."""

from __future__ import annotations

import json
import sys

import pytest
from conftest import REPO

sys.path.insert(0, str(REPO / "tools"))
import perf_records  # noqa: E402


def test_every_speed_figure_in_the_readme_and_docs_is_on_record():
    report = perf_records.check(perf_records.documents())
    assert not report.problems, "speed figures not traceable to a record:\n" + "\n".join(report.problems)
    assert not report.unrecorded, "speed figures measured before records were kept (rerun them for a record, or drop them):\n" + "\n".join(
        f"{block.path.relative_to(REPO)}:{block.start}: {block.target}" for block in report.unrecorded)


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_the_rule(tmp_path):
    record = _write(tmp_path, "run.json", json.dumps({"results": {"seconds": [1.49, 0.89], "rate": 9_291_234, "ratio": 3.79, "share": 0.123,
                                                                  "label": "2.0 s inside a string is not a number of the record"}}))
    text = f"""# A page

It took 1.5 s, unmarked.

<!-- record: {record} -->
It took 1.5 s and then 0.9 s, at 9.29 M points/s.

<!-- record: {record} -->
Runs of 1.5 and 2.0 s: the second is not in the record.

<!-- record: none (measured before records were kept; rerun tools/x.py) -->
It took 7 minutes.

<!-- record: n/a (a setting) -->
A stamp every 1 s.

```bash
tool --run   # about 25 s: code is not read
```

Numbers in code, `sleep 3 s`, and without units (30 scans, 2 threads) are not speed figures.

<!-- record: {record} -->
| row | s | input pts/s | vs numpy | share |
|---|---|---|---|---|
| `ebs`, 2 threads | 1.49 | 9.29 M | ×3.8 | 12 % |

| method | kernel |
|---|---|
| `s-bki` | 0.3 m, 7 cells |
"""
    report = perf_records.check([_write(tmp_path, "page.md", text)], repo=tmp_path)
    assert len(report.problems) == 2, report.problems
    assert "page.md:3: speed figures (1.5)" in report.problems[0] and "no <!-- record" in report.problems[0]
    assert report.problems[1].endswith(": 2.0")  # a number inside one of the record's strings does not count
    assert [b.start for b in report.unrecorded] == [12] and [b.start for b in report.not_measured] == [15]


def test_a_page_record_covers_the_blocks_without_their_own_marker(tmp_path):
    record = _write(tmp_path, "run.json", json.dumps({"seconds": 155.2}))
    page = _write(tmp_path, "page.md", f"# Study\n\n<!-- page-record: {record} -->\nWritten in 155 s.\n\nThen 156 s.\n")
    report = perf_records.check([page], repo=tmp_path)
    assert len(report.problems) == 1 and report.problems[0].endswith("156")


def _integration_record(tmp_path):
    import bench_integrate

    def row(seconds, updates, voxels, workers):
        return {"seconds": seconds, "all_seconds": [seconds], "voxel_updates": updates, "voxels": voxels, "workers": workers,
                "summary_seconds": 0.0123, "free": 1, "occupied": voxels - 1, "kept_or_training_points": 10}

    like_for_like = ["s-bki-compat@fr4", "ebs-release"]
    rows = {name: row(0.2 + 0.01 * i, 1_000_000 + i, 5000 + i, 2) for i, name in enumerate(bench_integrate.METHODS)}
    rows["numpy:ebs"] = {"seconds": 0.9, "voxel_updates": 10, "voxels": 5000}
    for name in like_for_like:
        for threads in (1, 2):
            rows[f"{name}@{threads}t"] = row(0.5 / threads, 3_000_000, 225_872, threads)
    cpp_rate = {(name, t): 100_000.0 * t for name in like_for_like for t in (1, 2)}
    cpp_rate[("ebs", 2)] = cpp_rate[("ebs-release", 2)]
    bench_integrate.compare_rows(rows, 1_800_000, cpp_rate)
    results = bench_integrate.integration_results(
        rows, scans=30, n_points=1_800_000, device="cpu", repeats=3, free_resolutions=["4"], thread_counts=(1, 2), like_for_like=like_for_like,
        cpp_path=REPO / "docs/cpp_side_by_side.json", cpp_source="timed beside us", cpp_rate=cpp_rate, release_after_cut={"ebs": 1}, problems=[])
    from bench_record import write_record

    return write_record("bench_integrate", results, folder=tmp_path)


def test_the_integration_table_is_generated_from_its_record(tmp_path):
    record = _integration_record(tmp_path)
    doc = _write(tmp_path, "performance.md", """# Performance

<!-- record: none (measured before records were kept); table: bench_integrate -->
| row | input pts/s | vs original C++ |
|---|---|---|
| `ebs` | 9.29 M | ×25.8 |

<!-- record: none (measured before records were kept) (caption: bench_integrate) -->
*One run, before records.*

After the table.
""")
    perf_records.regenerate(doc, record, repo=tmp_path)
    text = doc.read_text()
    assert f"<!-- record: {record.name}; table: bench_integrate -->" in text and "before records" not in text
    assert "| `s-bki`, sbki mode, free_res 4, 1 / 2 threads |" in text and "| `ebs`, RELLIS-3D preset (2 threads) |" in text
    assert "×45.0 vs EvSemMap EBS 200 k (its best: 2 threads), other map semantics" in text  # 1.8 M points in 0.2 s against 200 k/s
    assert text.rstrip().endswith("After the table.")
    report = perf_records.check([doc], repo=tmp_path)
    assert not report.problems and not report.unrecorded
    perf_records.regenerate(doc, record, repo=tmp_path)  # again: the same page
    assert doc.read_text() == text


def test_the_caption_says_when_the_cpp_was_timed_on_another_day(tmp_path):
    """Ratios against C++ figures of another day compare two VMs, not two programs side by side: said so."""
    record = json.loads(_integration_record(tmp_path).read_text())
    day = record["utc"][:10]
    record["results"]["cpp"]["summary"] = f"the originals timed on this machine kind on {day}"
    assert "not beside this run" not in perf_records.bench_integrate_caption(record, "r.json")
    record["results"]["cpp"]["summary"] = "the originals timed on this machine kind on 2026-12-02"
    if day != "2026-12-02":
        assert f"The C++ was timed on 2026-12-02, not beside this run ({day})" in perf_records.bench_integrate_caption(record, "r.json")


def test_the_caption_says_whether_the_cpp_ran_on_the_same_cpu_model(tmp_path):
    # VMs of the project's machine kind have come with an AMD EPYC or an Intel Xeon: a ratio against the
    # C++ timed on the other one compares two CPUs as well, and the caption says which case it is.
    (tmp_path / "cpp.json").write_text(json.dumps({"measured": {"machine": "2 vCPU AMD EPYC (Firecracker VM), 24 GB, Debian 12"}}))
    record = {"machine": {"cpu_model": "AMD EPYC"}, "results": {"cpp": {"file": "cpp.json"}}}
    assert "is the one the C++ was timed on" in perf_records._cpp_cpu_note(record, repo=tmp_path)
    record["machine"]["cpu_model"] = "Intel(R) Xeon(R) Processor"
    assert "compare two CPUs as well" in perf_records._cpp_cpu_note(record, repo=tmp_path)
    record["results"]["cpp"]["file"] = "absent.json"
    assert perf_records._cpp_cpu_note(record, repo=tmp_path) == ""


def test_the_side_by_side_record_states_both_sides_compiler_flags():
    flags = json.loads((REPO / "docs/cpp_side_by_side.json").read_text())["measured"]["compiler_flags"]
    assert "-O3" in flags["originals"] and "no -march" in flags["originals"]
    assert "-march=native" in flags["ours"] and "-march=native" in flags["march_native"]
    assert flags["march_native_ebs_cells"] == 225_864
    performance = (REPO / "docs/performance.md").read_text()
    assert "### Compiler flags on both sides" in performance and "225,864 cells instead of 225,872" in performance
    assert "performance.md#compiler-flags-on-both-sides" in (REPO / "docs/compatibility.md").read_text()


def test_a_record_states_how_warp_builds_cpu_kernels(tmp_path):
    pytest.importorskip("warp")
    from bench_record import write_record

    from evsemmap_warp.core.warp_runtime import init_warp

    wp = init_warp()
    record = json.loads(write_record("trial", {"n": 1}, folder=tmp_path).read_text())
    assert record["warp_build"]["cpu_compiler_flags"] == wp.config.cpu_compiler_flags and record["results"] == {"n": 1}


def test_ratios_in_prose_are_speed_figures(tmp_path):
    record = _write(tmp_path, "ab.json", json.dumps({"results": {"ours_over_reference": [0.9061, 0.927]}}))
    text = f"""<!-- record: {record} -->
free_res 0.5 took x0.906 the time and free_res 4 ×0.93; then x0.95, which the record does not hold.

A Brier score ×100, a x86-64 build and 2x as long are not ratios of a run.
"""
    report = perf_records.check([_write(tmp_path, "page.md", text)], repo=tmp_path)
    assert len(report.problems) == 1 and report.problems[0].endswith(": 0.95"), report.problems
