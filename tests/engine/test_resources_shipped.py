"""Every file in resources/ is shipped by a (non-editable) install, and found there."""

from __future__ import annotations

import tomllib
from pathlib import Path

import kneegui.resources as resources

ROOT = Path(__file__).resolve().parents[2]


def test_data_files_cover_every_resource():
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    data_files = config["tool"]["setuptools"]["data-files"]
    shipped = {
        path.relative_to(ROOT / "resources")
        for patterns in data_files.values()
        for pattern in patterns
        for path in ROOT.glob(pattern)
    }
    present = {
        p.relative_to(ROOT / "resources") for p in (ROOT / "resources").rglob("*") if p.is_file()
    }
    assert present and present == shipped
    # each file lands under share/kneegui/<its folder in the repository>
    for target, patterns in data_files.items():
        for pattern in patterns:
            assert target == "share/kneegui/" + str(Path(pattern).parent)


def test_installed_copy_is_found_without_a_source_tree(tmp_path, monkeypatch):
    installed = tmp_path / "share" / "kneegui" / "resources"
    installed.mkdir(parents=True)
    monkeypatch.setattr(resources, "__file__", str(tmp_path / "site" / "kneegui" / "x.py"))
    monkeypatch.setattr(resources.sysconfig, "get_path", lambda name: str(tmp_path))
    assert resources._find_resources_dir() == installed
