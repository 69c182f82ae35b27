"""every import of rocoma_can/, drivers/ and controllers/: the import contract: dependencies point
one way, core <- drivers <- node, record, fleet, live, ros2 <- runtime <- cli, and controllers see
the core and the joint types they command only; inside drivers/, the stages point one way too
(protocol <- files <- plan <- link <- bringup <- cycle <- commission <- sim <- hardware). Read from
the source (every import statement, at any depth, relative ones resolved), so a violation fails the
fast suite wherever it hides; and the CLI's verbs start without numpy.

import-linter cannot check this project: drivers/ and controllers/ are mapped into the
rocoma_can namespace by setuptools (package-dir), and it walks the root package's folder.
"""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest
from fixtures.paths import ROOT

from rocoma_can.cli.main import COMMAND_MODULES

#: folder -> package it is imported as
PACKAGES = {ROOT / "rocoma_can": "rocoma_can", ROOT / "drivers": "rocoma_can.drivers",
            ROOT / "controllers": "rocoma_can.controllers"}
#: rank of each part of the package: a module imports its own rank or lower
RANK = {"core": 0, "eds": 0, "drivers": 1, "node": 2, "record": 2, "fleet": 2, "live": 2,
        "ros2": 2, "runtime": 3, "cli": 4}
#: drivers/ by stage, bottom to top: a drivers module imports its own stage or one before it
#: (hardware.py, at the top of drivers/, wires them all; sim/ is a drive, built on them too)
DRIVER_STAGES = ("protocol", "files", "plan", "link", "bringup", "cycle", "commission", "sim",
                 "hardware")
#: what the controllers may use besides the core
CONTROLLERS_MAY = ("rocoma_can.drivers.protocol.joints",)


def _modules() -> dict[str, Path]:
    found = {}
    for folder, package in PACKAGES.items():
        for path in folder.rglob("*.py"):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join([package, *parts])] = path
    return found


MODULES = _modules()


def _part(module: str) -> str:
    """Which part of the package a rocoma_can module belongs to."""
    parts = module.split(".")
    if len(parts) == 1 or parts[1] not in RANK and parts[1] != "controllers":
        return "core"
    return parts[1]


def _stage(module: str) -> int:
    """Rank of a drivers module's stage; the package itself re-exports names from the
    stages, so it ranks above them all."""
    parts = module.split(".")
    return DRIVER_STAGES.index(parts[2]) if len(parts) > 2 else len(DRIVER_STAGES)


def _imports(module: str, path: Path) -> list[tuple[int, str]]:
    """(line, imported module) for every import in the file, relative ones resolved."""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            # ``from pkg import module`` imports the module
            found += [(node.lineno, f"{target}.{a.name}" if f"{target}.{a.name}" in MODULES
                       else target) for a in node.names]
    return [(line, name) for line, name in found if name.split(".")[0] == "rocoma_can"]


def test_dependencies_point_one_way():
    broken = []
    for module, path in MODULES.items():
        part = _part(module)
        for line, target in _imports(module, path):
            other = _part(target)
            if part == "controllers":
                ok = other in ("core", "controllers") or target.startswith(CONTROLLERS_MAY)
            elif other == "controllers":
                ok = part in ("runtime", "cli")  # the failproof layer is wired by the system
            elif (module, target) == ("rocoma_can.__main__", "rocoma_can.cli.main"):
                ok = True  # ``python -m rocoma_can`` is the command
            else:
                ok = RANK[other] <= RANK[part]
            if ok and part == other == "drivers":
                ok = _stage(target) <= _stage(module)
            if not ok:
                broken.append(f"{path.relative_to(ROOT)}:{line}: {part} imports {target}")
    assert not broken, "\n".join(sorted(set(broken)))


def test_the_contract_sees_a_violation(tmp_path):
    """The check itself: a drivers module importing the runtime is caught."""
    bad = tmp_path / "bad.py"
    bad.write_text("from ..runtime import config\n")
    imports = _imports("rocoma_can.drivers.bad", bad)
    assert imports == [(1, "rocoma_can.runtime.config")]
    assert RANK[_part(imports[0][1])] > RANK[_part("rocoma_can.drivers.bad")]


def test_the_contract_sees_a_stage_imported_upwards():
    """Within drivers/: a plan module importing the cycle is caught, the cycle importing the
    plan is not."""
    assert _stage("rocoma_can.drivers.cycle.command") > _stage("rocoma_can.drivers.plan.config")
    assert all((ROOT / "drivers" / stage).is_dir() or stage == "hardware"
               for stage in DRIVER_STAGES)


@pytest.mark.parametrize("module", ["rocoma_can.cli", *COMMAND_MODULES])
def test_the_cli_verbs_start_without_numpy(module):
    """``rocoma-can --help`` and every verb's parser load without numpy (a CLI that talks to
    a manager over SDO starts in a fraction of the time)."""
    code = (f"import sys, {module}; "
            "sys.exit('numpy imported' if 'numpy' in sys.modules else 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr or done.stdout
