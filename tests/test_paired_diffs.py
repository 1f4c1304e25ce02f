"""tools/paired_diffs.py: a method's paired differences against others, seed by seed, from a study's spread.json."""

import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))
import paired_diffs  # noqa: E402


def test_differences_are_paired_by_seed_and_lead_needs_every_mean_above_zero(tmp_path, capsys):
    spread = {"weak": {"new": {"mIoU": [30.0, 40.0, 20.0]}, "ebs": {"mIoU": [25.0, 41.0, 14.0]}, "convbki": {"mIoU": [31.0, 40.5, 19.0]}},
              "sure": {"new": {"mIoU": [60.0, 61.0, 62.0]}, "ebs": {"mIoU": [59.0, 60.0, 61.0]}, "convbki": {"mIoU": [58.0, 59.0, 60.0]}}}
    rows = paired_diffs.rows(spread, "new", ["ebs", "convbki"])
    assert rows[0] == ("weak", [30.0, 40.0, 20.0], {"ebs": [5.0, -1.0, 6.0], "convbki": [-1.0, -0.5, 1.0]})
    (tmp_path / "set").mkdir()
    (tmp_path / "set" / "spread.json").write_text(json.dumps(spread))
    paired_diffs.main([str(tmp_path / "set" / "spread.json"), "--method", "new", "--against", "ebs", "convbki"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[2].startswith("| set / weak | 30.0 ± 10.0 | +3.3 ± 3.8 (+5.0 / -1.0 / +6.0) | -0.2 ± 1.0") and lines[2].endswith("| no |")
    assert lines[3].endswith("| yes |")
