"""tools/house_counts.py counts what it says, on a small tree made here."""

import sys
import textwrap

from conftest import REPO

sys.path.insert(0, str(REPO / "tools"))
import house_counts  # noqa: E402

sys.path.remove(str(REPO / "tools"))


def _write(path, text):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))


def test_the_counts_of_a_small_tree(tmp_path):
    long_body = "".join(f"    x{i} = {i}\n" for i in range(85))
    _write(tmp_path / "evsemmap_warp/core/voxel_map.py", """
        import os
        class VoxelMap:
            def grow(self): return self._rows
            def scatter(self): os._exit(0)
            def _rows(self): pass
        """)
    _write(tmp_path / "evsemmap_warp/apps/mapper.py", "def _validate(x):\n    return x\n\ndef long():\n" + long_body)
    _write(tmp_path / "tools/bench.py", """
        from evsemmap_warp.apps.mapper import _validate
        def run(mapper): return mapper._rows(), mapper.public
        """)
    _write(tmp_path / "docs/bench/a.json", "{}")
    _write(tmp_path / "docs/bench/b.json", "{}")
    _write(tmp_path / "docs/page.md", "from [the record](bench/a.json)\n")
    _write(tmp_path / "README.md", "")
    counts = house_counts.count(tmp_path)
    assert counts.map_entry_points == ["grow", "scatter"]
    assert counts.largest_module["module"] == "evsemmap_warp/apps/mapper.py"
    assert counts.largest_class == {"class": "evsemmap_warp/core/voxel_map.py:VoxelMap", "lines": 4, "methods": 3}
    assert [f.split(" ")[1] for f in counts.long_functions] == ["long"]
    # os._exit is the standard library's; _validate imported and _rows read from another module are the project's
    assert counts.private_names_across_modules == ["tools/bench.py:2 imports _validate from evsemmap_warp.apps.mapper",
                                                   "tools/bench.py:3 reads mapper._rows"]
    assert (counts.records_cited, counts.records_not_cited) == (["a.json"], ["b.json"])
    assert "| functions over 80 lines | 1 |" in house_counts.table(counts)
