"""A method against others in a seeded study, seed by seed: its mIoU (mean ± sd over the seeds) and its paired
differences (each seed's, their mean ± sd) per condition, from the study's ``spread.json`` (``evsemmap
experiment``), as a Markdown table; a condition where its mean difference against every other is above 0
"leads".

    python tools/paired_diffs.py STUDY_OUT/spread.json [MORE/spread.json ...] --method ebs-learned --against ebs convbki s-csm
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path


def rows(spread: dict, method: str, against: list[str]) -> list[tuple[str, list[float], dict[str, list[float]]]]:
    """Per condition: (name, the method's mIoU per seed, {other: the method's minus the other's, per seed})."""
    out = []
    for condition, methods in spread.items():
        ours = methods[method]["mIoU"]
        out.append((condition, ours, {other: [a - b for a, b in zip(ours, methods[other]["mIoU"], strict=True)] for other in against}))
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("spreads", nargs="+", type=Path)
    parser.add_argument("--method", required=True)
    parser.add_argument("--against", nargs="+", required=True)
    args = parser.parse_args(argv)

    def mean_sd(values: list[float], sign: str = "") -> str:
        return f"{statistics.mean(values):{sign}.1f} ± {statistics.stdev(values):.1f}"

    print(f"| study / condition | `{args.method}` mIoU | " + " | ".join(f"− {o}" for o in args.against) + " | leads all |")
    print("|---|---|" + "---|" * len(args.against) + "---|")
    for path in args.spreads:
        study = path.parent.name
        for condition, ours, differences in rows(json.loads(path.read_text()), args.method, args.against):
            cells = [f"{mean_sd(d, '+')} ({' / '.join(f'{x:+.1f}' for x in d)})" for d in differences.values()]
            leads = all(statistics.mean(d) > 0 for d in differences.values())
            print(f"| {study} / {condition} | {mean_sd(ours)} | " + " | ".join(cells) + f" | {'yes' if leads else 'no'} |")


if __name__ == "__main__":
    main()
