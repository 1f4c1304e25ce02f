"""The documentation's code runs: every fenced code block of README.md and docs/ is run here, on tiny
synthetic data, or is marked as needing data the user must bring. The configuration reference names
every config key, and the API reference covers every module.

Conventions for a page's code blocks (this test enforces them):

* every fence names its language: ``bash`` and ``python`` blocks are run; a ``yaml`` block with
  ``title="NAME"`` is written to the file NAME for the commands after it (and parsed); other ``yaml``
  blocks are parsed; ``text`` blocks are output or layouts, never commands;
* ``<!-- needs-data: WHAT -->`` on the line above a fence: the block needs data the user brings (a
  dataset download, the project's ../shared folder, a cluster), and is not run;
* ``<!-- test-command -->`` above the README's test command: CI runs it (``.ci/run``);
* ``<!-- docs-test: after PAGE -->`` anywhere in a page: it continues in the folder PAGE's commands
  left behind (it uses what that page made, as its text says).

A page's blocks run in order in one folder, with ``configs/``, ``examples/``, ``tests/`` and ``tools/``
linked from the checkout, as a user in the checkout runs them. ``evsemmap`` commands run in this process
(``cli.main``), sized for a test by ``shrink``: the same commands, on tiny data. Install
commands (``python3 -m venv``, ``pip install``, ``pip wheel``) and ``mkdocs build`` are checked, not
run: CI runs them from a fresh clone.
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import pkgutil
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from conftest import REPO

DOC_FILES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
LANGUAGES = {"bash", "python", "yaml", "text"}
FENCE = re.compile(r"^```(\S*)(.*)$")
MARKER = re.compile(r"^<!--\s*(test-command|needs-data:\s*(?P<what>.*?))\s*-->$")
AFTER = re.compile(r"<!--\s*docs-test:\s*after\s+(\S+)\s*-->")
LINKED = ("configs", "examples", "tests", "tools")

# The stand-in for every built-in experiment config (``evsemmap demo``, ``evsemmap experiment NAME``):
# the same stages on two tiny worlds, one epoch of a tiny network, the condition and methods the
# pages' commands read back (maps/in-domain/ebs.npz, s-bki.npz).
TINY_STUDY = """
name: {name}
sequences:
  train: {{world: tiny, seed: 3, frames: 4}}
  test: {{world: tiny}}
networks:
  net: {{train_on: [train], epochs: 1, batch_size: 2, input_size: [64, 128]}}
conditions:
  in-domain: {{network: net, sequence: test}}
mapping_preset: offroad
methods: [s-bki, ebs]
"""

@dataclasses.dataclass
class Block:
    """One fenced code block of a page."""

    path: Path
    line: int
    language: str
    info: str
    marker: str | None
    text: str

    @property
    def where(self) -> str:
        return f"{self.path.relative_to(REPO)}:{self.line}"

    @property
    def title(self) -> str | None:
        match = re.search(r'title="([^"]+)"', self.info)
        return match.group(1) if match else None


def blocks_of(path: Path) -> list[Block]:
    """Every fenced block of a markdown file, with the marker comment on the line above it."""
    lines = path.read_text().split("\n")
    out, i = [], 0
    while i < len(lines):
        match = FENCE.match(lines[i])
        if not match:
            i += 1
            continue
        above = next((lines[j].strip() for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
        out.append(Block(path, i + 1, match.group(1), match.group(2).strip(), above if above.startswith("<!--") else None,
                         "\n".join(lines[i + 1:end])))
        i = end + 1
    return out


def page_name(path: Path) -> str:
    return "README.md" if path == REPO / "README.md" else path.relative_to(REPO / "docs").as_posix()


def page_path(name: str) -> Path:
    return REPO / "README.md" if name == "README.md" else REPO / "docs" / name


# ------------------------------------------------------------------------------------------ conventions
def test_every_block_is_run_or_marked():
    wrong = []
    for path in DOC_FILES:
        for block in blocks_of(path):
            if block.language not in LANGUAGES:
                wrong.append(f"{block.where}: a fence must name one of {sorted(LANGUAGES)}, not {block.language!r}")
            if block.marker is not None:
                match = MARKER.match(block.marker)
                if match is None:
                    wrong.append(f"{block.where}: unknown marker {block.marker!r}")
                elif match.group(1).startswith("needs-data") and not match.group("what"):
                    wrong.append(f"{block.where}: needs-data must say what the user brings")
            if block.language == "text" and re.search(r"^\s*(evsemmap|python3?|pip) ", block.text, re.M):
                wrong.append(f"{block.where}: commands in a text block are not run; make it a bash block")
        for name in AFTER.findall(path.read_text()):
            if not page_path(name).exists():
                wrong.append(f"{page_name(path)}: docs-test after {name}: no such page")
    assert not wrong, "\n".join(wrong)


def test_the_readme_keeps_its_test_command_where_ci_reads_it():
    blocks = [b for b in blocks_of(REPO / "README.md") if b.marker == "<!-- test-command -->"]
    assert len(blocks) == 1 and blocks[0].language == "bash"
    command = blocks[0].text.strip()
    ci = (REPO / ".ci/run").read_text()
    assert "awk '/<!-- test-command -->/{getline; getline; print; exit}' README.md" in ci
    # the line awk prints is the command itself: the marker, the fence, then the command
    lines = (REPO / "README.md").read_text().split("\n")
    at = lines.index("<!-- test-command -->")
    assert lines[at + 1] == "```bash" and lines[at + 2] == command
    assert command.endswith("python -m pytest") and "pip install" in command
    check_install_commands(command, blocks[0].where)


def test_readme_is_a_front_page():
    lines = (REPO / "README.md").read_text().split("\n")
    assert len(lines) <= 210, f"README.md has {len(lines)} lines; reference material belongs in docs/"


def test_the_readmes_python_loop_shows_progress():
    # A user who copies the README's loop onto a long drive should see its rate and ETA, as the commands show them.
    block = next(b for b in blocks_of(REPO / "README.md") if b.language == "python")
    loop = next(line for line in block.text.split("\n") if line.startswith("for scan in "))
    assert loop.startswith("for scan in tqdm("), loop


# ------------------------------------------------------------------------------------------ install commands
def _pyproject():
    import tomllib

    return tomllib.loads((REPO / "pyproject.toml").read_text())


def _torch_pin() -> str:
    test_command = next(b for b in blocks_of(REPO / "README.md") if b.marker == "<!-- test-command -->").text
    return re.search(r"torch==([\w.]+)", test_command).group(1)


def check_install_commands(line: str, where: str) -> list[list[str]]:
    """Check the install segments of a command line against pyproject.toml (extras that exist, the one
    torch pin); return the other segments, to be run."""
    extras = set(_pyproject()["project"]["optional-dependencies"])
    rest = []
    for argv in _segments(line):
        if argv[:3] == ["python3", "-m", "venv"] or argv[:1] in (["."], ["source"]):
            continue
        if argv[:2] == ["pip", "install"]:
            for arg in argv[2:]:
                if arg.startswith("torch"):
                    assert arg == f"torch=={_torch_pin()}", f"{where}: {arg}: the README pins torch=={_torch_pin()}"
                for group in re.findall(r"\[([\w,]+)\]", arg):
                    unknown = set(group.split(",")) - extras
                    assert not unknown, f"{where}: {arg}: no extra {sorted(unknown)} in pyproject.toml (it has {sorted(extras)})"
            continue
        if argv[:2] == ["pip", "wheel"]:
            assert "--no-deps" in argv, f"{where}: a wheel of this package alone is built with --no-deps"
            continue
        if argv[:1] == ["mkdocs"]:
            assert " ".join(argv) == "mkdocs build --strict" and "mkdocs build --strict" in (REPO / ".ci/run").read_text(), where
            continue
        rest.append(argv)
    return rest


def _segments(text: str) -> list[list[str]]:
    """The commands of a bash block: continuation lines joined, comments dropped, split at ``&&``."""
    joined = re.sub(r"\\\n\s*", " ", text)
    out = []
    for line in joined.split("\n"):
        words = shlex.split(line, comments=True)
        current: list[str] = []
        for word in words:
            if word == "&&":
                out.append(current)
                current = []
            else:
                current.append(word)
        if current:
            out.append(current)
    return out


# ------------------------------------------------------------------------------------------ running pages
def _free_port() -> str:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return str(s.getsockname()[1])


def _has(argv: list[str], flag: str) -> bool:
    return any(a == flag or a.startswith(flag + "=") for a in argv)


def shrink(argv: list[str]) -> list[str]:
    """``argv`` (after ``evsemmap``) sized for the test; otherwise the command runs as written.

    synth: a built-in preset other than tiny becomes tiny; view: --no-serve on a free port (it would
    serve until stopped); batch: at most 2 workers; train-seg: 1 epoch of a small network on small
    images; eval-seg: small images; train-convbki: 1 epoch of 2-scan windows. (``experiment`` and
    ``demo`` run TINY_STUDY in place of a built-in study: ``PageRunner._stand_in_studies``.)"""
    from evsemmap_warp.synthetic.preset import available_presets

    argv = list(argv)
    command = argv[0]
    if command == "synth":
        if "--world" in argv:
            at = argv.index("--world") + 1
            if argv[at] in available_presets():
                argv[at] = "tiny"
        else:
            argv += ["--world", "tiny"]
    elif command == "view":
        argv += [] if "--no-serve" in argv else ["--no-serve"]
        argv += [] if _has(argv, "--port") else ["--port", _free_port()]
    elif command == "batch" and not _has(argv, "--workers"):
        argv += ["--workers", str(min(2, os.cpu_count() or 1))]
    elif command == "train-seg":
        argv += ["--epochs", "1", "--input-size", "32", "64", "--width", "8", "--aspp-channels", "8", "--batch-size", "2",
                 "--synthetic-frames", "8"]
    elif command == "eval-seg":
        argv += ["--input-size", "32", "64"]
    elif command == "train-convbki":
        argv += ["--epochs", "1", "--window-scans", "2", "--queries", "200"]
    return argv


class PageRunner:
    """Runs the pages' blocks, each page in its own folder; a page that continues another starts from a
    copy of the folder that page left behind."""

    def __init__(self, root: Path):
        self.root = root
        self.finished: dict[str, Path] = {}
        self.batch_stores: set[Path] = set()

    def run(self, name: str, monkeypatch) -> Path:
        if name in self.finished:
            return self.finished[name]
        path = page_path(name)
        folder = self.root / name.replace("/", "__")
        after = AFTER.findall(path.read_text())
        if after:
            shutil.copytree(self.run(after[0], monkeypatch), folder, symlinks=True)
        else:
            folder.mkdir(parents=True)
            for linked in LINKED:
                (folder / linked).symlink_to(REPO / linked)
        study = folder / "tiny_study.yaml"
        namespace: dict = {"__name__": "__docs__"}
        with monkeypatch.context() as patch:
            patch.chdir(folder)
            self._stand_in_studies(patch, study)
            for block in blocks_of(path):
                if block.marker is not None or block.language == "text":
                    continue
                if block.language == "yaml":
                    data = yaml.safe_load(block.text)
                    if block.title:
                        (folder / block.title).write_text(block.text + "\n")
                    assert data is not None, block.where
                elif block.language == "python":
                    exec(compile(block.text, block.where, "exec"), namespace)
                elif block.language == "bash":
                    for argv in check_install_commands(block.text, block.where):
                        self._command(argv, block, folder)
        self.finished[name] = folder
        return folder

    @staticmethod
    def _stand_in_studies(patch, study: Path) -> None:
        from evsemmap_warp.apps import experiment

        real = experiment.load_experiment

        def load(name_or_path, quick=False):  # a built-in study's --quick is still too slow for a page's test
            if not Path(name_or_path).exists() and (experiment.experiments_dir() / f"{name_or_path}.yaml").exists():
                study.write_text(TINY_STUDY.format(name=name_or_path))
                config, _ = real(study)
                return config, study
            return real(name_or_path, quick=quick)

        patch.setattr(experiment, "load_experiment", load)

    def _command(self, argv: list[str], block: Block, folder: Path) -> None:
        from evsemmap_warp.apps.cli import main

        if argv[0] == "evsemmap":
            if argv[1] == "batch" and "--out" in argv:
                # A second batch into a finished store only resumes it ("resuming: 50 of 50 chunks are mapped
                # already"): a page that shows two runs must give each its own --out, or the second shows nothing.
                out = (folder / argv[argv.index("--out") + 1]).resolve()
                assert out not in self.batch_stores, f"{block.where}: `{shlex.join(argv)}` writes into {out.name}, " \
                    "which an earlier batch command of the page finished: it would only resume; give it its own --out"
                self.batch_stores.add(out)
            if "--executor" in argv and argv[argv.index("--executor") + 1] == "ray":
                pytest.importorskip("ray", reason=f"{block.where}: the ray extra is not installed")
            try:
                code = main(shrink(argv[1:]))
            except SystemExit as exc:  # argparse: --help, or a flag it refuses
                code = exc.code
            assert code == 0, f"{block.where}: `{shlex.join(argv)}` exited with {code}"
        elif argv[0] in ("python", "python3") and len(argv) > 1 and argv[1].split("/")[0] in ("examples", "tools"):
            done = subprocess.run([sys.executable, *argv[1:]], cwd=folder, capture_output=True, text=True, timeout=600,
                                  env=os.environ | {"PYTHONPATH": str(REPO)})
            assert done.returncode == 0, f"{block.where}: `{shlex.join(argv)}` failed:\n{done.stderr[-3000:]}"
        else:
            raise AssertionError(f"{block.where}: the docs test does not know how to run `{shlex.join(argv)}`; "
                                 "run it here or mark the block")


RUNNABLE = [page_name(p) for p in DOC_FILES
            if any(b.marker is None and b.language in ("bash", "python", "yaml") for b in blocks_of(p))]


@pytest.fixture(scope="module")
def runner(tmp_path_factory):
    return PageRunner(tmp_path_factory.mktemp("docs"))


@pytest.mark.parametrize("page", RUNNABLE)
def test_the_page_runs(page, runner, monkeypatch):
    runner.run(page, monkeypatch)


# ------------------------------------------------------------------------------------------ generated pages
def _docs_hooks():
    sys.path.insert(0, str(REPO / "tools"))
    try:
        import docs_hooks
    finally:
        sys.path.remove(str(REPO / "tools"))
    return docs_hooks


def test_the_configuration_reference_names_every_key():
    hooks = _docs_hooks()
    page = hooks.config_reference_markdown()
    missing, unexplained, listed = [], [], set()
    for config in hooks.config_files():
        for section in config.sections:
            listed.add(section.cls)
            renamed = dict(section.renamed)
            comments = hooks.field_comments(section.cls)
            prefix = "" if section.key.startswith("(") else section.key + "."
            for name in section.fields or [f.name for f in dataclasses.fields(section.cls)]:
                if f"| `{prefix}{renamed.get(name, name)}` |" not in page:
                    missing.append(f"{section.key}: {name}")
                if not comments.get(name):
                    unexplained.append(f"{section.cls.__name__}.{name}")
    assert not missing, f"keys missing from the configuration reference: {missing}"
    assert not unexplained, f"config fields without a comment beside them in the code (the reference's meaning column): {unexplained}"
    # every config dataclass of the config modules is on the page (a new section cannot be left out)
    from evsemmap_warp import config as run_config
    from evsemmap_warp.apps import experiment
    from evsemmap_warp.synthetic import preset
    from evsemmap_warp.terrain import config as terrain_config

    run_config_modules = [importlib.import_module(f"evsemmap_warp.config.{m.name}") for m in pkgutil.iter_modules(run_config.__path__)]
    for module in (*run_config_modules, experiment, preset, terrain_config):
        for value in vars(module).values():
            # a private dataclass is the loader's own state, not a section of a file
            if (dataclasses.is_dataclass(value) and isinstance(value, type) and value.__module__ == module.__name__
                    and not value.__name__.startswith("_")):
                # TerrainConfig holds the layers and costs sections (listed) and the file they came from
                assert value in listed or value.__name__ == "TerrainConfig", f"{module.__name__}.{value.__name__} is not on the page"
    # and every key of the run config's sections is one the loader accepts
    sections = run_config.MAPPING_SECTIONS
    all_mapping = {f.name for f in dataclasses.fields(run_config.MappingConfig) if f.name not in sections}
    all_mapping |= {f"{name}.{f.name}" for name, cls in sections.items() for f in dataclasses.fields(cls)}
    assert all(f"| `mapping.{name}` |" in page for name in all_mapping)


def test_the_configuration_page_has_its_marker():
    hooks = _docs_hooks()
    assert hooks.CONFIG_MARKER in (REPO / "docs/configuration.md").read_text()
    assert hooks.BENCH_MARKER in (REPO / "docs/performance.md").read_text()


def test_the_bench_records_list_reads_records(tmp_path):
    hooks = _docs_hooks()
    assert "No run records" in hooks.bench_records_markdown(tmp_path)
    (tmp_path / "bench_x-20260101T000000Z.json").write_text(
        '{"tool": "bench_x", "command": ["python", "tools/bench_x.py"], "utc": "2026-01-01T00:00:00+00:00", "commit": "abc", '
        '"tree_clean": true, "machine": {"cpu_model": "CPU", "cores": 2}, "results": {}}')
    table = hooks.bench_records_markdown(tmp_path)
    assert "`bench_x`" in table and "bench/bench_x-20260101T000000Z.json" in table


def test_the_api_reference_covers_every_module():
    reference = "\n".join(p.read_text() for p in (REPO / "docs/reference").glob("*.md"))
    documented = set(re.findall(r"^::: (\S+)", reference, re.M))
    modules = set()
    for root, prefix in ((REPO / "evsemmap_warp", "evsemmap_warp"), (REPO / "kernels", "kernels")):
        for path in root.rglob("*.py"):
            parts = path.relative_to(root).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            if any(part.startswith("_") for part in parts):
                continue
            modules.add(".".join((prefix, *parts)))
    assert not modules - documented, f"modules missing from docs/reference/: {sorted(modules - documented)}"
    assert not documented - modules, f"docs/reference/ names modules that do not exist: {sorted(documented - modules)}"
