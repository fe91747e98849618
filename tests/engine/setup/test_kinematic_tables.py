"""Shipped kinematic tables: values from their formulas, sources, user tables, errors."""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from kneegui.errors import SetupError
from kneegui.setup.kinematic_tables import (
    TABLES_DIR,
    read_table_csv,
    resolve_table,
    shipped_tables,
    table_names,
)


def _table_builder():
    """The builder of the shipped tables is a script (scripts/build_kinematic_tables.py), not an
    engine module; its formulas are the reference the shipped files are checked against."""
    path = Path(__file__).resolve().parents[3] / "scripts" / "build_kinematic_tables.py"
    spec = importlib.util.spec_from_file_location("build_kinematic_tables", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_builder = _table_builder()
build, walker1988_internal_rotation = _builder.build, _builder.walker1988_internal_rotation


def test_walker_exact_cubic():
    t = resolve_table("tibial_rotation", "walker1988")
    d = np.arange(-10.0, 151.0)
    np.testing.assert_allclose(
        t.value_at(d), 0.3695 * d - 2.958e-3 * d**2 + 7.666e-6 * d**3, atol=1e-8
    )
    assert t.value_at(120.0) == pytest.approx(14.991648, abs=1e-6)
    # between the 1-degree rows the linear interpolation stays within 1e-3 deg of the cubic
    mid = np.arange(-9.5, 150.0, 1.0)
    assert np.max(np.abs(t.value_at(mid) - walker1988_internal_rotation(mid))) < 1e-3


@pytest.mark.parametrize(
    ("name", "at120"), [("walker1988_scaled20", 20.0), ("asano2001", 29.1), ("johal2005", 20.0)]
)
def test_scaled_tables_keep_walkers_shape(name, at120):
    t = resolve_table("tibial_rotation", name)
    assert t.value_at(120.0) == pytest.approx(at120, abs=1e-8)
    d = np.arange(-10.0, 151.0, 5.0)
    np.testing.assert_allclose(
        t.value_at(d),
        walker1988_internal_rotation(d) * at120 / walker1988_internal_rotation(120.0),
        atol=1e-8,
    )


def test_defaults():
    assert resolve_table("tibial_rotation", "default").name == "walker1988_scaled20"
    pf = resolve_table("patellar_flexion", "default")
    np.testing.assert_allclose(
        pf.value_at([-5.0, 0.0, 9.0, 90.0, 140.0]), [-3.25, 0.0, 5.85, 58.5, 91.0]
    )
    tilt = resolve_table("patellar_tilt", "default")
    np.testing.assert_allclose(
        tilt.value_at([-5.0, 0.0, 15.0, 30.0, 60.0, 90.0, 120.0, 140.0]),
        [0.0, 0.0, 4.4, 8.8, 6.7, 4.6, 4.6, 4.6],
    )
    assert tilt.change(9.0, 90.0) == pytest.approx(4.6 - 8.8 * 9 / 30)


def test_every_shipped_row_has_a_source():
    index = shipped_tables()
    assert {t.quantity for t in index} == {"tibial_rotation", "patellar_flexion", "patellar_tilt"}
    for quantity in ("tibial_rotation", "patellar_flexion", "patellar_tilt"):
        assert sum(t.default for t in index if t.quantity == quantity) == 1
    for t in index:
        assert t.source.strip()
        with open(TABLES_DIR / t.file, newline="") as fh:
            rows = list(csv.DictReader(fh))
        assert rows and all(r["source"].strip() for r in rows)
    assert "walker1988" in table_names("tibial_rotation")


def test_shipped_files_are_what_the_builder_writes(tmp_path):
    build(tmp_path)
    for path in sorted(TABLES_DIR.glob("*.csv")):
        if path.name == "condyle_fit_limits.csv":
            continue
        assert (tmp_path / path.name).read_bytes() == path.read_bytes(), path.name


def test_user_table(tmp_path):
    path = tmp_path / "mine.csv"
    path.write_text("flexion_deg,value_deg,source\n0,0,me\n60,12,me\n120,18,me\n")
    t = resolve_table("tibial_rotation", str(path))
    assert t.value_at(90.0) == pytest.approx(15.0)
    assert t.value_at(200.0) == pytest.approx(18.0)  # held beyond the last row
    assert t.sources == ("me",)
    assert resolve_table("tibial_rotation", "mine.csv", base_dir=tmp_path).value_at(30) == 6.0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("flexion,value_deg\n0,0\n1,1\n", "no column 'flexion_deg'"),
        ("flexion_deg,value_deg\n0,0\n", "at least 2 rows"),
        ("flexion_deg,value_deg\n0,0\n0,1\n", "strictly increasing"),
        ("flexion_deg,value_deg\n0,0\n10,abc\n", "line 3: not a number"),
        ("flexion_deg,value_deg\n0,0\n10,inf\n", "line 3: not finite"),
    ],
)
def test_bad_user_table(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(SetupError, match=message) as info:
        read_table_csv(path, "patellar_tilt")
    assert info.value.key == "kinematics.patellar_tilt"


def test_unknown_names():
    with pytest.raises(SetupError, match="unknown table 'walker'") as info:
        resolve_table("tibial_rotation", "walker")
    assert "walker1988" in str(info.value)
    with pytest.raises(SetupError, match="not found"):
        resolve_table("patellar_flexion", "nowhere/table.csv")
    with pytest.raises(SetupError, match="unknown kinematic quantity"):
        resolve_table("knee_spin", "default")


def test_edited_user_table_is_reread(tmp_path):
    path = tmp_path / "mine.csv"
    path.write_text("flexion_deg,value_deg\n0,0\n100,10\n")
    assert resolve_table("patellar_tilt", str(path)).value_at(50.0) == pytest.approx(5.0)
    path.write_text("flexion_deg,value_deg\n0,0\n100,20\n")
    assert resolve_table("patellar_tilt", str(path)).value_at(50.0) == pytest.approx(10.0)
