"""tools/module-map, docs/architecture.md, docs/api.md and tests/: the module map is the one the
docstrings give now, the API page documents every public module and names no module that is
gone, and every test module says in its first line what it tests.

The map is generated (tools/module-map); a module added, moved or renamed without running the
tool fails here, with the command that fixes it. The generator itself is tested on a small
tree of its own: what it reads, the order it lists folders in, what it refuses.
"""
from __future__ import annotations

import ast
import importlib
import importlib.machinery
import importlib.util
import re
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest
from fixtures.paths import ROOT

TOOL = ROOT / "tools" / "module-map"


def _tool() -> ModuleType:
    """tools/module-map as a module (a script without .py: loaded by path)."""
    loader = importlib.machinery.SourceFileLoader("module_map", str(TOOL))
    spec = importlib.util.spec_from_loader("module_map", loader)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["module_map"] = module  # dataclasses look their module up by name
    loader.exec_module(module)
    return module


def test_the_architecture_page_has_the_map_the_source_gives() -> None:
    result = subprocess.run([sys.executable, str(TOOL), "--check"], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def _write(path: Path, docstring: str, body: str = "") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f'"""{docstring}"""\n{body}', encoding="utf-8")


@pytest.fixture
def tool(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    """The generator pointed at a tree of tmp_path: a core with two folders, one importing
    the other, and a page with the markers."""
    mm = _tool()
    monkeypatch.setattr(mm, "ROOT", tmp_path)
    monkeypatch.setattr(mm, "PAGE", tmp_path / "page.md")
    monkeypatch.setattr(mm, "SOURCES", (("core", "core"),))
    _write(tmp_path / "core" / "__init__.py", "The core. More prose that the map leaves out.")
    _write(tmp_path / "core" / "zeta" / "__init__.py", "Zeta, at the bottom.")
    _write(tmp_path / "core" / "zeta" / "codec.py", "Codecs, e.g. one frame. Not this.")
    _write(tmp_path / "core" / "alpha" / "__init__.py", "Alpha, on top of zeta.")
    _write(tmp_path / "core" / "alpha" / "uses.py", "Uses zeta's codec | a pipe.",
           "from ..zeta import codec\n")
    (tmp_path / "page.md").write_text(f"# Page\n\n{mm.MARK_BEGIN}\nold\n{mm.MARK_END}\n\nEnd.\n",
                                      encoding="utf-8")
    return mm


def test_the_map_lists_every_folder_in_import_order_and_every_module(tool: ModuleType) -> None:
    assert tool.main([]) == 0
    page = tool.PAGE.read_text(encoding="utf-8")
    assert page.startswith("# Page\n\n") and page.endswith("\n\nEnd.\n")
    assert "\nold\n" not in page
    # zeta before alpha, which imports it (alphabetically it would be the other way round)
    assert page.index("  zeta/") < page.index("  alpha/")
    assert "core/                      The core. (import core)" in page
    assert "| `codec.py` | Codecs, e.g. one frame. |" in page
    assert "| `uses.py` | Uses zeta's codec \\| a pipe. |" in page
    assert tool.main(["--check"]) == 0


def test_a_module_added_later_makes_the_page_stale(tool: ModuleType,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert tool.main([]) == 0
    _write(tool.ROOT / "core" / "zeta" / "wire.py", "Bits on the wire.")
    assert tool.main(["--check"]) == 1
    assert "run tools/module-map" in capsys.readouterr().err
    assert tool.main([]) == 0
    assert "| `wire.py` | Bits on the wire. |" in tool.PAGE.read_text(encoding="utf-8")


def test_a_module_without_a_docstring_is_refused_by_name(
        tool: ModuleType, capsys: pytest.CaptureFixture[str]) -> None:
    (tool.ROOT / "core" / "bare.py").write_text("X = 1\n", encoding="utf-8")
    before = tool.PAGE.read_text(encoding="utf-8")
    assert tool.main([]) == 1
    assert "core/bare.py: no docstring" in capsys.readouterr().err
    assert tool.PAGE.read_text(encoding="utf-8") == before


def test_a_page_without_the_markers_is_refused(tool: ModuleType,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    tool.PAGE.write_text("# Page\n", encoding="utf-8")
    assert tool.main(["--check"]) == 1
    assert "markers are missing" in capsys.readouterr().err


API_PAGE = ROOT / "docs" / "api.md"
_AUTOMODULE = re.compile(r"^\.\. automodule:: (\S+)", re.MULTILINE)


def _documented() -> list[str]:
    return _AUTOMODULE.findall(API_PAGE.read_text(encoding="utf-8"))


def _packages() -> list[str]:
    """Every package of the three source folders, by import name (from the map's reading)."""
    found = []
    todo = list(_tool().read_sources())
    while todo:
        package = todo.pop()
        found.append(package.import_name)
        todo += package.packages
    return sorted(found)


def test_the_api_page_names_only_modules_that_exist() -> None:
    gone = []
    for name in _documented():
        try:
            importlib.import_module(name)
        except ModuleNotFoundError:
            gone.append(name)
    assert not gone, f"docs/api.md documents modules that do not exist: {gone}"


def test_the_api_page_documents_every_module_a_package_exports_from() -> None:
    """A package's ``__all__`` is its public face: the module each of those names is defined
    in is on the API page."""
    public = set()
    for package in _packages():
        module = importlib.import_module(package)
        for name in getattr(module, "__all__", ()):
            defined_in = getattr(getattr(module, name), "__module__", "")
            if defined_in.startswith("rocoma_can"):
                public.add(defined_in)
    assert public, "no package exports a name: the check would prove nothing"
    missing = sorted(public - set(_documented()))
    assert not missing, f"docs/api.md: no automodule for the public modules {missing}"


TESTS = ROOT / "tests"
#: a path in a docstring's first line: a/b.py, a/b/, a/*.py, tools/vcan-run, README.md
_PATH = re.compile(r"[\w.*-]+(?:/[\w.*-]*)+|[\w-]+\.(?:py|md)\b")


def _names_code(line: str) -> bool:
    """Whether a line names a file or folder of the checkout (rocoma_can/ may be left out:
    ``record/rings.py``)."""
    for found in _PATH.findall(line):
        candidate = found.strip(".,:;)`")
        for base in (ROOT, ROOT / "rocoma_can"):
            if any(base.glob(candidate)) or (base / candidate).exists():
                return True
    return False


def test_every_test_module_names_what_it_tests_in_its_first_line() -> None:
    silent = []
    for path in sorted(TESTS.rglob("test_*.py")):
        docstring = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
        if not _names_code(docstring.split("\n", 1)[0]):
            silent.append(str(path.relative_to(ROOT)))
    assert not silent, f"test modules whose docstring's first line names no module: {silent}"


def test_no_two_test_files_share_a_name() -> None:
    """pytest imports test modules by their file name (tests/ has no ``__init__.py``)."""
    seen: dict[str, list[str]] = {}
    for path in TESTS.rglob("test_*.py"):
        seen.setdefault(path.name, []).append(str(path.relative_to(ROOT)))
    shared = {name: paths for name, paths in seen.items() if len(paths) > 1}
    assert not shared, f"test files that share a name: {shared}"
