"""The public surface: what ``evsemmap_warp`` exports (``__all__``) is the API the reference lists and the
pages' code imports; a module with a leading underscore is private to its package."""

import ast
import inspect
import re
import types
from pathlib import Path

import evsemmap_warp

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "evsemmap_warp"
PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]


def _public_subpackages() -> dict[str, types.ModuleType]:
    return {name: value for name in evsemmap_warp.__all__ if isinstance(value := getattr(evsemmap_warp, name), types.ModuleType)}


def test_every_exported_name_resolves_and_says_what_it_is():
    assert len(set(evsemmap_warp.__all__)) == len(evsemmap_warp.__all__)
    undocumented = [name for name in evsemmap_warp.__all__
                    if (inspect.isclass(obj := getattr(evsemmap_warp, name)) or inspect.isfunction(obj) or inspect.ismodule(obj))
                    and not inspect.getdoc(obj)]
    assert not undocumented, f"exported without a docstring: {undocumented}"
    assert set(evsemmap_warp.__all__) <= set(dir(evsemmap_warp))
    for module in _public_subpackages().values():
        assert module.__all__ and all(hasattr(module, name) for name in module.__all__), module.__name__


def test_the_reference_lists_exactly_the_exported_names():
    text = (REPO / "docs/reference/index.md").read_text()
    table = text[text.index("| name | what |"):].split("\n\n")[0]
    first_cells = [row.split("|")[1] for row in table.splitlines()[2:]]
    listed = {name for cell in first_cells for name in re.findall(r"`([A-Za-z_]\w*)`", cell)}
    assert listed == set(evsemmap_warp.__all__), (f"exported but not listed: {sorted(set(evsemmap_warp.__all__) - listed)}; "
                                                  f"listed but not exported: {sorted(listed - set(evsemmap_warp.__all__))}")


def _python_blocks(path: Path):
    for match in re.finditer(r"^```python[^\n]*\n(.*?)^```", path.read_text(), re.M | re.S):
        yield match.group(1)


def test_the_pages_import_only_public_names():
    public = set(evsemmap_warp.__all__)
    subpackages = {f"evsemmap_warp.{name}": set(module.__all__) for name, module in _public_subpackages().items()}
    wrong = []
    for path in PAGES:
        for code in _python_blocks(path):
            for node in ast.walk(ast.parse(code)):
                if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("evsemmap_warp"):
                    allowed = public if node.module == "evsemmap_warp" else subpackages.get(node.module, set())
                    wrong += [f"{path.relative_to(REPO)}: from {node.module} import {a.name}" for a in node.names if a.name not in allowed]
                elif isinstance(node, ast.Import):
                    wrong += [f"{path.relative_to(REPO)}: import {a.name}" for a in node.names
                              if a.name.startswith("evsemmap_warp.") and a.name not in subpackages]
    assert not wrong, "pages import internal names (export them from evsemmap_warp, or show the CLI):\n" + "\n".join(wrong)


def _is_module(parts: list[str]) -> bool:
    where = PACKAGE.joinpath(*parts)
    return where.with_suffix(".py").is_file() or (where / "__init__.py").is_file()


def test_private_modules_are_imported_only_inside_their_package():
    wrong = []
    for path in PACKAGE.rglob("*.py"):
        package = path.relative_to(PACKAGE).parent.parts
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = list(package[:len(package) - node.level + 1]) if node.level > 1 else list(package)
                    target = base + (node.module.split(".") if node.module else [])
                    names = [target + [a.name] for a in node.names]
                elif (node.module or "").startswith("evsemmap_warp."):
                    names = [node.module.split(".")[1:] + [a.name] for a in node.names]
                else:
                    continue
                for parts in names:
                    # modules only: a private function of a module is that module's business
                    modules = [i for i in range(len(parts)) if _is_module(parts[:i + 1])]
                    private = [i for i in modules if parts[i].startswith("_") and not parts[i].startswith("__")]
                    if private and tuple(parts[:private[0]]) != package:
                        wrong.append(f"{path.relative_to(REPO)} imports {'.'.join(parts)}")
    assert not wrong, "a private module used outside its package:\n" + "\n".join(wrong)
