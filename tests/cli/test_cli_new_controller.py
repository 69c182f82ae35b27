"""rocoma_can/cli/scaffold.py: `rocoma-can new-controller`: the generated package's own tests pass
against this install."""
from __future__ import annotations

import os
import subprocess
import sys

from rocoma_can.cli.main import main


def test_generated_package_tests_pass(tmp_path, capsys):
    assert main(["new-controller", "my_pd", "--dir", str(tmp_path)]) == 0
    root = tmp_path / "my_pd"
    assert {p.name for p in root.iterdir()} == {"pyproject.toml", "my_pd", "tests", "README.md"}
    assert 'my_pd = "my_pd.controller:MyPd"' in (root / "pyproject.toml").read_text()
    # Not pip-installed into the shared venv: the module is found through PYTHONPATH, and
    # the entry-point test skips itself with the reason.
    env = dict(os.environ, PYTHONPATH=str(root))
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                             "-rs", str(root / "tests")], cwd=root, env=env,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "3 passed, 1 skipped" in result.stdout


def test_bad_names_and_existing_folders(tmp_path, capsys):
    assert main(["new-controller", "My-PD", "--dir", str(tmp_path)]) == 2
    assert main(["new-controller", "ok_name", "--dir", str(tmp_path)]) == 0
    assert main(["new-controller", "ok_name", "--dir", str(tmp_path)]) == 2
    assert "already exists" in capsys.readouterr().err  # a message: stderr (docs/cli.md)


def test_a_name_an_installed_controller_or_module_has_is_refused(tmp_path, capsys):
    """`new-controller pd` made a package whose entry point `pd` shadowed the shipped pd
    controller once installed (or was shadowed: the first installed wins, whichever that
    is), and `new-controller numpy` one whose module `numpy` shadowed NumPy for the whole
    environment. Nothing is written for either."""
    for name, taken in (("pd", "a controller"), ("damp", "a controller"),
                        ("torque_off", "a controller"), ("numpy", "a module"),
                        ("json", "a module"), ("can", "a module")):
        assert main(["new-controller", name, "--dir", str(tmp_path)]) == 2, name
        said = capsys.readouterr().err
        assert f"controller name {name!r} is taken: {taken} of that name is installed" \
            in said, said
    assert list(tmp_path.iterdir()) == []
