"""``evsemmap dump-config``: print the resolved configuration (mapping, dataset, terrain layers and costs)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import yaml

from ...config import load_config


def add_parser(sub) -> None:
    """Add ``dump-config`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("dump-config", help="print the resolved configuration (mapping, dataset, terrain layers and costs)")
    p.add_argument("configs", nargs="*")
    p.add_argument("--method", default=None)
    p.add_argument("--costs", type=Path, default=None, help="a terrain cost file laid over the default table (as evsemmap layers --costs)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Print the resolved configuration (mapping, dataset, pipeline, terrain layers and costs) as YAML."""
    resolved = load_config(args.configs, method=args.method)
    out = {"mapping": resolved.mapping.as_dict(every_key=True)}
    if resolved.dataset is not None:
        def plain(value):
            if dataclasses.is_dataclass(value):
                return {k: plain(v) for k, v in vars(value).items()}
            return list(value) if isinstance(value, tuple) else getattr(value, "value", value)

        out["dataset"] = {k: plain(v) for k, v in vars(resolved.dataset).items() if k != "bag" or resolved.dataset.kind == "bag"}
    if resolved.bin_frames != 1:
        out["pipeline"] = {"bin_frames": resolved.bin_frames}
    from ...terrain import load_terrain_config

    terrain = load_terrain_config(args.costs)
    out["terrain"] = {"source": terrain.source, "layers": _plain_dataclass(terrain.layers), "costs": _plain_dataclass(terrain.costs)}
    print(yaml.safe_dump(out, sort_keys=False), end="")
    return 0


def _plain_dataclass(value) -> dict:
    """A settings dataclass as YAML-ready values (tuples as lists)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(value).items()}
