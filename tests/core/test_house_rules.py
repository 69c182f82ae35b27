"""rocoma_can/, drivers/, controllers/, tests/, tools/: the house rules a reader relies on to find
things, read from the source: a public name means one thing across rocoma_can/, drivers/ and
controllers/ (``from x import Phase`` never picks the wrong one), and no module is longer than a
reader takes in (500 lines).

Function complexity (at most 15) is ruff's C901, configured in pyproject.toml and run by
tools/test's lint step."""
from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

from fixtures.paths import ROOT

#: the folders that ship, as the package they are imported as
PACKAGES = {"rocoma_can": "rocoma_can", "drivers": "rocoma_can.drivers",
            "controllers": "rocoma_can.controllers"}
#: names every module of a kind defines on purpose: a module's logger, a verb module's hook
#: that cli/main.py calls, the entry of a module that runs as a process of its own
CONVENTIONS = {"log", "register", "main"}
#: the longest module a reader takes in at once
MAX_LINES = 500
#: the frames the drives receive, torque-off first: the safety path's last step, read whole
#: in one sitting by a safety review
FRAMES_OUT = ROOT / "drivers" / "cycle" / "frames_out.py"


def _public_names(tree: ast.Module) -> set[str]:
    """Classes, functions and type aliases a module defines at its top level (a name in
    capitals is a constant, and constants are local facts: DEFAULT, TIMEOUT ...)."""
    names: set[str] = set()
    for node in tree.body:
        if isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names |= {t.id for t in targets if isinstance(t, ast.Name) and not t.id.isupper()}
    return {n for n in names if not n.startswith("_") and n not in CONVENTIONS}


def collisions(folders: dict[Path, str]) -> dict[str, list[str]]:
    """Public name -> the modules that define it, for names defined in more than one."""
    where: dict[str, set[str]] = defaultdict(set)
    for folder, package in folders.items():
        for path in sorted(folder.rglob("*.py")):
            module = ".".join([package, *path.relative_to(folder).with_suffix("").parts])
            for name in _public_names(ast.parse(path.read_text(), str(path))):
                where[name].add(module.removesuffix(".__init__"))
    return {name: sorted(mods) for name, mods in where.items() if len(mods) > 1}


def test_no_two_modules_define_the_same_public_name():
    found = collisions({ROOT / folder: package for folder, package in PACKAGES.items()})
    assert not found, "\n".join(f"{name}: {', '.join(mods)}" for name, mods in
                                sorted(found.items()))


def test_the_check_sees_a_collision(tmp_path):
    (tmp_path / "a.py").write_text("class Phase:\n    pass\nlog = None\n")
    (tmp_path / "b.py").write_text("Phase = int\nlog = None\nLIMIT = 1\n")
    (tmp_path / "c.py").write_text("LIMIT = 2\n_private = 1\n")
    assert collisions({tmp_path: "pkg"}) == {"Phase": ["pkg.a", "pkg.b"]}


def _python_files() -> list[Path]:
    """Every Python file of the checkout that is ours: modules, and tools/' scripts."""
    found = [path for folder in (*PACKAGES, "tests", "tools", "benchmarks")
             for path in sorted((ROOT / folder).rglob("*.py"))]
    return found + [path for path in sorted((ROOT / "tools").iterdir()) if path.is_file()
                    and path.read_bytes().startswith(b"#!/usr/bin/env python3")]


def test_no_module_is_over_500_lines():
    long = [f"{path.relative_to(ROOT)}: {n} lines" for path in _python_files()
            if (n := len(path.read_text().splitlines())) > MAX_LINES]
    assert not long, "\n".join(long)


def test_the_torque_off_path_reads_in_one_sitting():
    assert len(FRAMES_OUT.read_text().splitlines()) < 100
