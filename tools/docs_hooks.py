"""MkDocs hooks (``mkdocs.yml``: ``hooks``): the parts of the documentation generated from the code and
the committed records each time the site is built, so that they cannot drift from what they describe.

* ``<!-- generated: configuration-reference -->`` (docs/configuration.md): every key of every config
  file, read from the config dataclasses: the key, its type, its default and the comments written
  beside the field in the code (``config_reference_markdown``).
* ``<!-- generated: bench-records -->`` (docs/performance.md): the benchmark run records committed
  under ``docs/bench/`` (``bench_records_markdown``).

``tests/test_docs.py`` checks that the configuration reference names every field of every config
dataclass, so a new key cannot be left out of the page.
"""

from __future__ import annotations

import dataclasses
import enum
import inspect
import io
import json
import textwrap
import tokenize
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CONFIG_MARKER = "<!-- generated: configuration-reference -->"
BENCH_MARKER = "<!-- generated: bench-records -->"


@dataclass(frozen=True)
class Section:
    """One section of a config file: its dotted name as written in YAML, the dataclass that reads it,
    and which of its fields are keys (``None``: all of them)."""

    key: str
    cls: type
    fields: tuple[str, ...] | None = None
    renamed: tuple[tuple[str, str], ...] = ()  # (field, key as written in YAML)


@dataclass(frozen=True)
class ConfigFile:
    """A kind of config file: its title on the page, what reads it, and its sections in order."""

    title: str
    intro: str
    sections: tuple[Section, ...]


def config_files() -> list[ConfigFile]:
    """The config files a user writes, each with the dataclasses that read its sections."""
    from evsemmap_warp.apps.experiment import (AblationSpec, ConditionSpec, ConvBkiTraining, ExperimentConfig, NetworkSpec,
                                               SequenceSpec)
    from evsemmap_warp.config import MAPPING_SECTIONS, METHOD_KEYS, BagConfig, DatasetConfig, MappingConfig, RunConfig
    from evsemmap_warp.geometry.projection import ProjectionConfig
    from evsemmap_warp.synthetic.preset import (AppearanceParams, CameraParams, LidarParams, SynthPreset, TrajectoryParams,
                                                WorldParams)
    from evsemmap_warp.terrain.config import CostSettings, LayerSettings

    method_keys = tuple(sorted("method" if key == "name" else key for key in METHOD_KEYS))
    return [
        ConfigFile(
            "Mapping runs",
            "Method files (`configs/methods/`), presets (`configs/presets/`) and dataset configs "
            "(`configs/datasets/`), given to `evsemmap map`, `batch` and `dump-config` (or `load_config`) and "
            "merged in order, later files winning key by key. A method file's `method` section sets the switches "
            "below; every other number lives in `mapping`.",
            (Section("method", MappingConfig, method_keys, renamed=(("method", "name"),)),
             Section("mapping", MappingConfig, tuple(f.name for f in dataclasses.fields(MappingConfig) if f.name not in MAPPING_SECTIONS)),
             *(Section(f"mapping.{name}", cls) for name, cls in MAPPING_SECTIONS.items()),
             Section("dataset", DatasetConfig, tuple(f.name for f in dataclasses.fields(DatasetConfig) if f.name != "config_dir")),
             Section("dataset.bag", BagConfig),
             Section("pipeline", RunConfig, ("bin_frames",)))),
        ConfigFile(
            "Terrain layers and costs",
            "The cost table of `evsemmap layers --costs FILE`, laid over `configs/terrain/costs_v3.yaml`: a file "
            "overrides exactly the keys it names (class costs one by one); the layers' defaults below are that file's "
            "([Terrain layers](terrain.md) §4 gives the cost model).",
            (Section("layers", LayerSettings), Section("costs", CostSettings))),
        ConfigFile(
            "Synthetic worlds",
            "The world presets of `evsemmap synth --world NAME|FILE` and of an experiment's `sequences.NAME.world` "
            "(`configs/synthetic/`: `tiny`, `demo`, `default`, `long`).",
            (Section("(top level)", SynthPreset, ("name", "seed")), Section("world", WorldParams),
             Section("trajectory", TrajectoryParams), Section("lidar", LidarParams), Section("camera", CameraParams),
             Section("appearance", AppearanceParams))),
        ConfigFile(
            "Experiments",
            "The studies of `evsemmap experiment CONFIG` (`configs/experiments/`). `sequences`, `networks` and "
            "`conditions` map names of your choice to the entries below.",
            (Section("(top level)", ExperimentConfig, tuple(f.name for f in dataclasses.fields(ExperimentConfig)
                                                            if f.name not in ("projection", "ablation", "convbki"))),
             Section("sequences.NAME", SequenceSpec), Section("networks.NAME", NetworkSpec),
             Section("conditions.NAME", ConditionSpec), Section("ablation", AblationSpec),
             Section("projection", ProjectionConfig), Section("convbki", ConvBkiTraining))),
    ]


def field_comments(cls: type) -> dict[str, str]:
    """The comments written beside each field of a dataclass (or member of an enum) in its source: the
    one on the field's own line, after those on the lines just above it. A comment block ending in ':'
    heads every field below it up to the next blank line."""
    source = textwrap.dedent(inspect.getsource(cls))
    lines = source.splitlines()
    comments: dict[int, str] = {}
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            comments[token.start[0]] = token.string.lstrip("#").strip()
    out: dict[str, str] = {}
    heading, above = "", []
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped:
            heading, above = "", []
            continue
        if stripped.startswith("#"):
            above.append(comments.get(number, ""))
            continue
        if line.startswith("    ") and not line.startswith("     ") and (":" in stripped or "=" in stripped) \
                and not stripped.startswith(("def ", "@", "class ", "return", "if ", "for ", "raise")):
            name = stripped.split(":")[0].split("=")[0].strip()
            if name.isidentifier():
                block = " ".join(above)
                if block.endswith(":"):  # a heading over the fields below it
                    heading, block = block, ""
                elif block:  # a comment of its own ends the heading's group
                    heading = ""
                own = comments.get(number, "")
                out[name] = " ".join(part for part in (heading, block, own) if part)
        above = []
    return out


def _type_text(cls: type, field: dataclasses.Field) -> str:
    default = _default_value(field)
    if isinstance(default, enum.Enum):
        return "one of " + ", ".join(f"`{member.value}`" for member in type(default))
    text = str(field.type)
    optional = text.endswith(" | None")  # YAML's null is the None
    text = text.removesuffix(" | None")
    text = {"tuple[str, ...]": "list of str", "tuple[float, ...]": "list of numbers", "tuple": "list", "dict": "mapping",
            "float": "number", "int": "integer", "bool": "true / false", "str": "string"}.get(text, text)
    return text + " or null" if optional else text


def _default_value(field: dataclasses.Field):
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return dataclasses.MISSING


def _default_text(field: dataclasses.Field) -> str:
    value = _default_value(field)
    if value is dataclasses.MISSING:
        return "(required)"
    if dataclasses.is_dataclass(value):
        return "(a section)"
    if isinstance(value, enum.Enum):
        value = value.value
    if isinstance(value, tuple):
        value = list(value)
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if value is None:
        return "`null`"
    if value == "":
        return '`""`'
    return f"`{json.dumps(value) if isinstance(value, (list, dict)) else value}`"


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def section_markdown(section: Section) -> str:
    """The table of one section: key, type, default and the code's comment for each of its keys."""
    fields = {f.name: f for f in dataclasses.fields(section.cls)}
    names = section.fields if section.fields is not None else tuple(fields)
    comments = field_comments(section.cls)
    renamed = dict(section.renamed)
    prefix = "" if section.key.startswith("(") else section.key + "."
    rows = ["| key | type | default | meaning |", "|---|---|---|---|"]
    for name in names:
        field = fields[name]
        meaning = comments.get(name, "")
        default = _default_value(field)
        if isinstance(default, enum.Enum):
            values = field_comments(type(default))
            meaning = (meaning + " " if meaning else "") + "; ".join(
                f"`{member.value}`: {values[member.name]}" if values.get(member.name) else f"`{member.value}`" for member in type(default))
        rows.append(f"| `{prefix}{renamed.get(name, name)}` | {_cell(_type_text(section.cls, field))} | {_cell(_default_text(field))} | "
                    f"{_cell(meaning)} |")
    doc = inspect.getdoc(section.cls) or ""
    # a dataclass without a docstring gets one from dataclasses: its signature, which says nothing here
    intro = "" if doc.startswith(section.cls.__name__ + "(") else " ".join(doc.split("\n\n")[0].split()) + "\n\n"
    title = section.key if section.key.startswith("(") else f"`{section.key}`"
    return f"### {title}\n\n{intro}" + "\n".join(rows) + "\n"


def config_reference_markdown() -> str:
    """Every config file's sections as tables (the body of docs/configuration.md)."""
    parts = []
    for config in config_files():
        parts.append(f"## {config.title}\n\n{config.intro}\n")
        parts.extend(section_markdown(section) for section in config.sections)
    return "\n".join(parts)


def bench_records_markdown(folder: Path = REPO / "docs" / "bench") -> str:
    """A table of the benchmark run records in ``folder`` (tools/bench_record.py writes them), newest first."""
    records = []
    for path in sorted(folder.glob("*.json"), reverse=True):
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if not isinstance(record, dict) or "tool" not in record:
            continue
        machine = record.get("machine", {})
        commit = str(record.get("commit", ""))[:10] + ("" if record.get("tree_clean", True) else " (modified tree)")
        command = " ".join(str(part) for part in record.get("command", []))
        records.append(f"| [`{path.name}`](bench/{path.name}) | `{record['tool']}` | {record.get('utc', '')} | `{commit}` | "
                       f"{_cell(str(machine.get('cpu_model', '')))}, {machine.get('cores', '')} cores | `{_cell(command)}` |")
    if not records:
        return "*No run records are committed under `docs/bench/` yet.*\n"
    return "\n".join(["| record | tool | UTC | commit | machine | command |", "|---|---|---|---|---|---|", *records]) + "\n"


def on_page_markdown(markdown: str, page, config, files) -> str:
    """MkDocs hook: put the generated parts in place of their markers."""
    if CONFIG_MARKER in markdown:
        markdown = markdown.replace(CONFIG_MARKER, config_reference_markdown())
    if BENCH_MARKER in markdown:
        markdown = markdown.replace(BENCH_MARKER, bench_records_markdown())
    return markdown
