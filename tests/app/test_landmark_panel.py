"""The landmark panel shows how much the F-E axis depends on the picked condyle nodes."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.gui


def test_axis_spread_shown_and_updated_live(demo_window):
    ws, panel = demo_window.ws, demo_window.landmark_panel
    # the demo's condyles are exact circular arcs: the axis does not depend on the nodes
    assert ws.axes.sensitivity is not None
    assert "± 0.00 mm" in panel.labels["lateral_fit"].text()
    assert panel.labels["fe_spread"].text().startswith("0.00°")
    # add femur nodes inside the lateral circle (as a box pick through the bone would)
    axes = ws.axes
    femur = ws.setup.segment_nodes["femur"]
    rel = ws.coords[femur] - axes.lateral_center
    ml = rel @ axes.sagittal_normal
    dist = np.hypot(rel @ axes.anterior, rel @ axes.superior)
    radius = axes.lateral_fit.radius
    inside = (np.abs(ml) < 5.0) & (dist > radius - 6.0) & (dist < radius - 2.0)
    inside &= rel @ axes.anterior < 0.0  # behind the centre: on the posterior arc's side
    extra = ws.model.node_ids[femur[inside]][:8]
    assert len(extra) >= 3
    before = ws.axes.sensitivity.direction_spread_deg
    ws.add_condyle_ids("lateral_condyle", extra.tolist())
    assert ws.setup_problem is None, ws.setup_problem
    after = ws.axes.sensitivity
    assert after.direction_spread_deg > before + 0.05
    assert panel.labels["fe_spread"].text() == (
        f"{after.direction_spread_deg:.2f}°, centres {after.lateral_center_spread_mm:.2f} / "
        f"{after.medial_center_spread_mm:.2f} mm"
    )
    assert f"± {after.lateral_radius_spread_mm:.2f} mm" in panel.labels["lateral_fit"].text()


def test_axis_landmarks_are_shown_as_numbers(demo_window):
    """Axes given as points or nodes are shown with their coordinates, never a placeholder."""
    ws, panel = demo_window.ws, demo_window.landmark_panel
    landmarks = ws.setup_dict["landmarks"]
    for key in ("lr_axis", "femur_axis", "tibia_axis"):
        text = panel.labels[key].text()
        assert "xyz" not in text and text != "–", (key, text)
        for point in landmarks[key]:
            if isinstance(point, int):
                xyz = ws.model.coords[int(ws.model.node_index(point))]
                assert f"node {point} ({xyz[0]:.1f}, {xyz[1]:.1f}, {xyz[2]:.1f})" in text
            else:
                assert f"({point[0]:.1f}, {point[1]:.1f}, {point[2]:.1f})" in text
