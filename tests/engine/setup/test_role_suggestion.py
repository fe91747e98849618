"""Role suggestion from part titles (THUMS, GHBMC, VIVA+, PIPER-style names)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from kneegui.errors import SetupError
from kneegui.model import ElementBlock, Model, Part
from kneegui.setup import ROLES, suggest_roles
from kneegui.setup.roles import ROLE_PATTERNS_FILE, load_role_patterns, role_for_title, title_side

EXPECTED = {
    "FEMUR_CORTICAL_R": "femur",
    "Femur_Spongy": "femur",
    "Femur_Cortical_R": "femur",
    "Femur_R_cortical": "femur",
    "LX-Bone-Femur-Trabecular-R": "femur",
    "Femoral_Cartilage": "femur",
    "Tibia_Cortical_R": "tibia",
    "TIBIA_SPONGY_R": "tibia",
    "Fibula_R_trabecular": "fibula",
    "Patella_Cortical_R": "patella",
    "Flesh_Thigh": "flesh",
    "LX-Flesh-Calf-R": "flesh",
    "Muscle_Vastus_Lateralis": "flesh",
    "Rectus_Femoris": "flesh",
    "Tibialis_Anterior_R": "flesh",
    "Biceps_Femoris": "flesh",
    "Fat_Knee": "flesh",
    "Artery_Femoral_R": "flesh",
    "Vein_Popliteal": "flesh",
    "Nerve_Sciatic": "flesh",
    "Skin_LowerExt": "skin",
    "LX-Skin-R": "skin",
    "Lig_ACL": "ligament",
    "LX-Lig-MCL-R": "ligament",
    "PCL_R": "ligament",
    "Ligament_Collateral_Lateral": "ligament",
    "Meniscus_Med": "meniscus",
    "LX-Meniscus-Lateral-R": "meniscus",
    "Tendon_Patellar": "tendon",
    "Patellar_Ligament": "tendon",
    "Quadriceps_Tendon_R": "tendon",
    "Knee_Capsule": "capsule",
    "Pelvis_Cortical": "fixed",
    "Talus_R": "fixed",
    "Calcaneus": "fixed",
}
UNMATCHED = ["Part 17", "Airbag", "Cortical_Bone_17", "Seat_Foam"]


@pytest.mark.parametrize(("title", "role"), EXPECTED.items())
def test_title_patterns(title, role):
    assert role_for_title(title) == role
    assert role_for_title(title.upper()) == role
    assert role_for_title(title.lower()) == role


@pytest.mark.parametrize("title", UNMATCHED)
def test_unmatched_titles(title):
    assert role_for_title(title) is None


def _model_with_titles(titles):
    n = len(titles)
    coords = np.arange(3 * (n + 1), dtype=float).reshape(-1, 3)
    pids = np.arange(1, n + 1) * 10
    block = ElementBlock(
        "beam2", np.arange(1, n + 1), pids, np.column_stack([np.arange(n), np.arange(n) + 1])
    )
    parts = {int(p): Part(int(p), t) for p, t in zip(pids, titles, strict=True)}
    return Model(np.arange(1, n + 2), coords, {"beam2": block}, parts)


def test_suggest_roles_on_a_model():
    titles = [*EXPECTED, *UNMATCHED]
    model = _model_with_titles(titles)
    roles = suggest_roles(model)
    assert set(roles) == set(ROLES)
    by_pid = {pid: role for role, pids in roles.items() for pid in pids}
    for i, title in enumerate(titles):
        pid = (i + 1) * 10
        assert by_pid.get(pid) == EXPECTED.get(title), title


def test_side_filter_skips_the_other_leg():
    model = _model_with_titles(
        [
            "Femur_Cortical_R",
            "Femur_Cortical_L",
            "Femur_Spongy",
            "Flesh_Knee",
            "Tibia_Right",
            "Tibia Left",
        ]
    )
    roles = suggest_roles(model, side="right")
    assert roles["femur"] == [10, 30]
    assert roles["tibia"] == [50]
    assert roles["flesh"] == [40]  # no side token: kept
    left = suggest_roles(model, side="left")
    assert left["femur"] == [20, 30] and left["tibia"] == [60]
    with pytest.raises(SetupError):
        suggest_roles(model, side="up")


def test_title_side_tokens():
    assert title_side("LX-Bone-Femur-Cortical-R") == "right"
    assert title_side("Femur_L_cortical") == "left"
    assert title_side("FemurLeft") == "left"
    assert title_side("Skin_LowerExt") is None
    assert title_side("LX-Flesh") is None


def test_pattern_table_is_sourced_and_valid():
    patterns = load_role_patterns()
    assert {p.role for p in patterns} <= set(ROLES)
    with open(ROLE_PATTERNS_FILE, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(patterns)
    assert all(r["source"].strip() for r in rows)


def test_custom_pattern_table(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("order,role,pattern,source\n1,femur,^os_femoris$,mine\n")
    model = _model_with_titles(["os_femoris", "Femur"])
    roles = suggest_roles(model, patterns_path=path)
    assert roles["femur"] == [10]
    bad = tmp_path / "bad.csv"
    bad.write_text("order,role,pattern,source\n1,bone,femur,mine\n")
    with pytest.raises(SetupError, match="unknown role 'bone'"):
        suggest_roles(model, patterns_path=bad)
