"""The package layout shows the pipeline and imports run one way: applications -> core -> methods ->
data and geometry -> foundation (config, classes, voxel keys) -> kernels, with no import circles, lazy
imports inside functions included. Docs the code cites exist in the repository."""

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "evsemmap_warp"

# Lower layers never import higher ones; the same layer may import itself.
LAYERS = {
    "kernels": 0, "reference": 0,
    "config": 1, "classes": 1, "voxel_keys": 1, "frames": 1, "files": 1, "limits": 1,
    "geometry": 2,
    "data": 3,
    "methods": 4,
    "core": 5,
    "synthetic": 6, "segmentation": 6, "terrain": 6,
    "apps": 7, "live": 7,
    "__init__": 8, "__main__": 8,
}


def _module_name(path: Path) -> str:
    if path.is_relative_to(REPO / "kernels"):
        rel = Path("kernels") / path.relative_to(REPO / "kernels")
    else:
        rel = path.relative_to(PACKAGE)
    parts = list(rel.with_suffix("").parts)
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Package modules imported anywhere in the file (module level and inside functions)."""
    module = _module_name(path)
    package = module.split(".")[:-1] if not path.name == "__init__.py" else module.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)] if node.level > 1 else package
                target = base + (node.module.split(".") if node.module else [])
                names = [".".join(target + [a.name]) for a in node.names] if not node.module else [".".join(target)]
                found.update(n for n in names if n)
            elif node.module and node.module.startswith("evsemmap_warp."):
                found.add(node.module.removeprefix("evsemmap_warp."))
        elif isinstance(node, ast.Import):
            found.update(a.name.removeprefix("evsemmap_warp.") for a in node.names if a.name.startswith("evsemmap_warp."))
    return found


def _graph() -> dict[str, set[str]]:
    files = [p for p in PACKAGE.rglob("*.py")] + [p for p in (REPO / "kernels").rglob("*.py")]
    modules = {_module_name(p): p for p in files}
    graph = {}
    for name, path in modules.items():
        edges = set()
        for target in _imports(path):
            # "from ..methods import convbki" names a module; "from .x import f" names a function of x
            while target and target not in modules and target + ".__init__" not in modules:
                target = target.rpartition(".")[0]
            if target and target != name:
                edges.add(target)
        graph[name] = edges
    return graph


def _layer(module: str) -> int:
    return LAYERS[module.split(".")[0]]


def test_imports_run_one_way():
    wrong = [f"{a} -> {b}" for a, targets in _graph().items() for b in targets
             if not b.endswith("__init__") and _layer(a) < _layer(b)]
    assert not wrong, "imports against the layering: " + ", ".join(sorted(wrong))


def test_no_import_circles():
    graph = _graph()
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for nxt in graph.get(node, ()):
            if nxt.endswith("__init__") or nxt not in graph:
                continue
            if state.get(nxt) == 1:
                raise AssertionError("import circle: " + " -> ".join(stack[stack.index(nxt):] + [nxt]))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in graph:
        if node not in state:
            visit(node)


def test_every_layer_is_known_and_every_package_has_an_init():
    for path in PACKAGE.iterdir():
        if path.name.startswith(("_", ".")) and path.name != "__init__.py":
            continue
        if path.is_dir() and any(path.glob("*.py")):
            assert (path / "__init__.py").exists(), f"{path} lacks __init__.py: setup.py's find_packages would skip it"
        name = path.stem if path.suffix == ".py" else path.name
        if path.suffix == ".py" or path.is_dir() and any(path.glob("*.py")):
            assert name in LAYERS, f"{path.relative_to(REPO)} has no layer in tests/test_layout.py"


def test_code_cites_only_documents_the_repository_has():
    cited = re.compile(r"(?:spec \d|spec section|reference_sbki\.md|baselines\.md|stack_notes\.md|peer_timings\.md)", re.I)
    sections = re.compile(r"docs/(algorithm|compatibility)\.md §([\d.]+)")
    docs = {name: (REPO / "docs" / f"{name}.md").read_text() for name in ("algorithm", "compatibility")}
    for path in [*PACKAGE.rglob("*.py"), *(REPO / "kernels").rglob("*.py"), *(REPO / "configs").rglob("*.yaml")]:
        text = path.read_text()
        assert not cited.search(text), f"{path.relative_to(REPO)} cites a document outside the repository: {cited.search(text).group(0)}"
        for doc, section in sections.findall(text):
            first = section.split("-")[0].rstrip(".")
            assert f"§{first} " in docs[doc] or f"## {first}." in docs[doc], f"{path.relative_to(REPO)}: docs/{doc}.md has no §{first}"
