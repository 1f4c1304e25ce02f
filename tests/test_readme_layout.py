"""The README's layout section names every module of the package, every kernel module and every tool, so
that a newcomer's map of the tree is the tree."""

import fnmatch
import re

from conftest import REPO


def _layout_words() -> set[str]:
    text = (REPO / "README.md").read_text()
    block = re.search(r"## Layout\n\n```text\n(.*?)```", text, re.S)
    assert block, "README.md has no ## Layout section with a text block"
    return set(re.findall(r"[\w*.]+", block.group(1)))


def _named(path, words: set[str]) -> bool:
    names = {path.stem, path.name}
    return any(name in words or any("*" in w and fnmatch.fnmatch(name, w) for w in words) for name in names)


def test_the_layout_names_every_module_kernel_and_tool():
    words = _layout_words()
    files = [p for p in (REPO / "evsemmap_warp").rglob("*.py") if p.name != "__init__.py" and "reference" not in p.parts]
    files += [p for p in (REPO / "kernels").glob("*.py") if p.name != "__init__.py"]
    files += [p for p in (REPO / "tools").iterdir() if p.suffix in (".py", ".sh")]
    missing = sorted(str(p.relative_to(REPO)) for p in files if not _named(p, words))
    assert not missing, f"README.md's layout section does not name: {missing}"
    folders = {p.name for p in (REPO / "evsemmap_warp").iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert not {f"{f}/" for f in folders} - {w + "/" for w in words}, "a package folder is missing from the layout"
