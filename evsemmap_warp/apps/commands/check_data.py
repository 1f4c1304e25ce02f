"""``evsemmap check-data``: report what is missing or inconsistent in sequence folders or robot logs (exit 1 on problems)."""

from __future__ import annotations

from pathlib import Path

from ...config import load_config


def add_parser(sub) -> None:
    """Add ``check-data`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("check-data", help="report what is missing or inconsistent in sequence folders or robot logs (exit 1 on problems)")
    p.add_argument("paths", nargs="+", type=Path,
                   help="RELLIS-3D-layout folders, or robot logs (.bag, .mcap, .db3, ROS 2 bag folders; read as one sequence) "
                        "with the dataset configs or presets that say their topics (e.g. rellis3d-bag)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Report what is missing or inconsistent in the sequence folders or robot logs; exit code 1 when something is."""
    from ...config import is_robot_log
    from ...data.logs import check_log
    from ...data.sequences import check_sequence

    logs = [p for p in args.paths if is_robot_log(p)]
    # configs: YAML files and preset names (a bare word); a missing path is a folder to report, never a preset
    configs = [str(p) for p in args.paths if not is_robot_log(p) and (p.suffix in (".yaml", ".yml") or
                                                                     (not p.exists() and p.suffix == "" and len(p.parts) == 1))]
    folders = [p for p in args.paths if p not in logs and str(p) not in configs]
    if not logs and not folders:
        raise ValueError(f"check-data: none of {[str(p) for p in args.paths]} is a sequence folder or a robot log (configs and presets "
                         f"only say how to read logs)")
    reports = [check_sequence(d) for d in folders]
    if logs:
        reports.append(check_log(logs, _bag_config(logs, configs)))
    for report in reports:
        print(report.text())
    return 0 if all(r.ok for r in reports) else 1


def _bag_config(logs, configs):
    """The dataset.bag settings of the given config files and preset names (defaults without any)."""
    run = load_config([str(p) for p in logs] + list(configs))
    return run.dataset.bag
