"""The import contract in pyproject.toml ([tool.importlinter], docs/architecture.md) holds, and it
would catch an upward import.

The contract is checked statically by import-linter over every import statement, including
imports inside functions and under ``TYPE_CHECKING``; tests/engine/test_engine_imports.py checks
at run time that importing the engine loads no GUI module.

The proof runs the same checker on a copy of the packages with one bad import injected and
requires it to fail naming that import; an unmodified copy must pass, so a failure can only come
from the injection.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import importlinter  # noqa: F401  (a test dependency: fail here, loudly, when it is missing)
import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("kneegui", "app", "bench")

LINT = (
    "import sys\n"
    "from importlinter.cli import lint_imports\n"
    "sys.exit(lint_imports(config_filename='pyproject.toml', no_cache=True, no_logo=True))\n"
)


def lint_imports(tree: Path) -> subprocess.CompletedProcess:
    """Run import-linter on the project rooted at ``tree`` (its packages first on the path)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(tree), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return subprocess.run(
        [sys.executable, "-c", LINT],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_the_project_keeps_its_import_contract():
    result = lint_imports(ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 broken" in result.stdout


@pytest.fixture
def tree_copy(tmp_path: Path) -> Path:
    """The Python packages and pyproject.toml copied to a scratch folder."""
    for package in PACKAGES:
        shutil.copytree(
            ROOT / package,
            tmp_path / package,
            ignore=shutil.ignore_patterns("__pycache__", "results", "*.png", "*.csv", "*.json"),
        )
    shutil.copy2(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def _append(path: Path, code: str) -> None:
    path.write_text(path.read_text(encoding="utf-8") + "\n" + code + "\n", encoding="utf-8")


#: (file to edit, code appended, text the report must contain)
UPWARD_IMPORTS = {
    "model imports the repositioner": (
        "kneegui/model.py",
        "from kneegui.reposition import Repositioner  # noqa",
        "kneegui.model is not allowed to import kneegui.reposition",
    ),
    "setup imports posing (a loop)": (
        "kneegui/setup/format.py",
        "from kneegui.kinematics import posing  # noqa",
        "kneegui.setup is not allowed to import kneegui.kinematics",
    ),
    "geometry imports the setup for a type hint (a loop)": (
        "kneegui/geometry/axes.py",
        "from typing import TYPE_CHECKING  # noqa\n"
        "if TYPE_CHECKING:\n    from kneegui.setup.format import JointSetup  # noqa",
        "kneegui.geometry is not allowed to import kneegui.setup",
    ),
    "quality imports the mesh improvement": (
        "kneegui/quality/metrics.py",
        "def _later():\n    from kneegui.meshopt import smoother  # noqa",
        "kneegui.quality is not allowed to import kneegui.meshopt",
    ),
    "the engine imports the GUI": (
        "kneegui/cli.py",
        "def _gui():\n    import app.workspace  # noqa",
        "kneegui is not allowed to import app",
    ),
    "the engine imports the benchmarks": (
        "kneegui/commands/demo.py",
        "import bench.pose_bench  # noqa",
        "kneegui is not allowed to import bench",
    ),
    "the engine imports Qt": (
        "kneegui/geometry/transforms.py",
        "import PySide6  # noqa",
        "kneegui is not allowed to import PySide6",
    ),
}


def test_an_unmodified_copy_passes(tree_copy):
    result = lint_imports(tree_copy)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize("case", list(UPWARD_IMPORTS))
def test_an_upward_import_breaks_the_contract(tree_copy, case):
    file, code, expected = UPWARD_IMPORTS[case]
    _append(tree_copy / file, code)
    result = lint_imports(tree_copy)
    assert result.returncode != 0, result.stdout
    assert expected in result.stdout, result.stdout
    module = file.removesuffix(".py").replace("/", ".")
    assert module in result.stdout, result.stdout  # the report names the offending module


def test_a_new_engine_package_must_be_placed_in_the_layers(tree_copy):
    (tree_copy / "kneegui" / "unplaced").mkdir()
    (tree_copy / "kneegui" / "unplaced" / "__init__.py").write_text('"""Not in the contract."""\n')
    result = lint_imports(tree_copy)
    assert result.returncode != 0, result.stdout
    assert "kneegui.unplaced" in result.stdout, result.stdout
