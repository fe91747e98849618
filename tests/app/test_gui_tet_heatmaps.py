"""Heat-maps on a tetrahedral model (issue 25): the tet measures offered first and drawn, the
Jacobian (1 on every tet) not first; volume change on solids only, area change on shells."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from PySide6.QtCore import Qt
from PySide6.QtGui import QImage

from app.main import build_parser
from app.workspace import HEATMAP_METRICS
from kneegui.io.lsdyna import read_deck
from kneegui.model import ElementBlock
from kneegui.quality import compute_quality
from kneegui.topology import SHELL_TYPES, SOLID_TYPES, block_offsets

from .conftest import wait_idle

pytestmark = pytest.mark.gui

#: The six tetrahedra of a hexahedron around its diagonal 0-6 (Kuhn), all positive.
KUHN = ((0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6))


def _tet_demo(deck):
    """The demo leg with every hexahedron split into six tets (same nodes, parts and setup)."""
    model = read_deck(deck)
    hexes = model.blocks["hex8"]
    conn = hexes.conn[:, np.array(KUHN)].reshape(-1, 4)
    blocks = {
        "tet4": ElementBlock(
            "tet4",
            np.arange(1, len(conn) + 1) + 10_000_000,
            np.repeat(hexes.part_ids, len(KUHN)),
            conn,
        )
    }
    blocks.update({t: b for t, b in model.blocks.items() if t != "hex8"})
    return replace(model, blocks=blocks, source=None)


@pytest.fixture
def tet_window(window, qtbot, leg_files):
    deck, setup = leg_files
    model = _tet_demo(deck)
    assert "hex8" not in model.blocks and len(model.blocks["tet4"]) > 0
    window.ws.load(model, setup)
    wait_idle(qtbot, window.ws)
    window.viewport.flush()
    return window


def test_tet_model_offers_and_draws_the_tet_measures(tet_window, qtbot):
    ws, vp, panel = tet_window.ws, tet_window.viewport, tet_window.quality_panel
    offered = [panel.metric.itemData(i) for i in range(panel.metric.count())]
    assert offered == ws.heatmap_metrics()
    assert offered[:4] == ["tet_collapse", "dihedral_min", "dihedral_max", "vol_skew"]
    # the demo's skin is quad shells, so the Jacobian stays on offer, after the tet measures
    assert offered.index("jacobian") > offered.index("vol_skew")
    assert ws.metric == "tet_collapse" and panel.metric.currentData() == "tet_collapse"
    panel.mode.setCurrentIndex(panel.mode.findData("quality"))
    vp.flush()
    assert vp._scalar_title == "Tet collapse"
    values = ws.element_values("tet_collapse")
    q = compute_quality(ws.coords, ws.model.blocks)
    start = block_offsets(ws.model.blocks)["tet4"]
    tets = slice(start, start + len(ws.model.blocks["tet4"]))
    np.testing.assert_array_equal(values[tets], q["tet4"].tet_collapse)
    shown = np.concatenate([vp.surfaces[p].mesh.cell_data["value"] for p in vp.surfaces])
    shown = shown[np.isfinite(shown)]
    assert len(shown) and np.ptp(shown) > 0.1  # a real heat-map, not a constant colour
    assert 0 < shown.min() < shown.max() <= 1 + 1e-12
    panel.refresh()
    assert f"worst tet collapse {q['tet4'].tet_collapse.min():.3f}" in panel.stats.text()
    # the dihedral angles, then the worst list (smallest first) points at the worst tet
    panel.metric.setCurrentIndex(panel.metric.findData("dihedral_min"))
    vp.flush()
    assert vp._scalar_title == "Tet min dihedral (°)"
    dihedral = ws.element_values("dihedral_min")
    np.testing.assert_array_equal(dihedral[tets], q["tet4"].dihedral_min)
    panel.refresh()
    first = int(panel.worst.item(0).data(Qt.ItemDataRole.UserRole))
    assert dihedral[first] == np.nanmin(dihedral)


def test_volume_change_is_solids_only_and_area_change_its_own_metric(tet_window, qtbot):
    ws, panel = tet_window.ws, tet_window.quality_panel
    qtbot.waitUntil(lambda: ws.poser is not None, timeout=60000)
    ws.set_flexion(60.0)
    wait_idle(qtbot, ws)
    offsets = block_offsets(ws.model.blocks)
    solid = np.zeros(ws.model.n_elements, bool)
    for etype, block in ws.model.blocks.items():
        if etype in SOLID_TYPES:
            solid[offsets[etype] : offsets[etype] + len(block)] = True
    shell = np.zeros_like(solid)
    for etype, block in ws.model.blocks.items():
        if etype in SHELL_TYPES:
            shell[offsets[etype] : offsets[etype] + len(block)] = True
    volume = ws.element_values("volume_change")
    area = ws.element_values("area_change")
    assert np.isnan(volume[~solid]).all() and np.isfinite(volume[solid]).all()
    assert np.isnan(area[~shell]).all() and np.isfinite(area[shell]).all()
    assert np.nanmax(np.abs(volume)) > 0 and np.nanmax(np.abs(area)) > 0  # the leg moved
    panel.mode.setCurrentIndex(panel.mode.findData("quality"))
    for key in ("volume_change", "area_change"):
        panel.metric.setCurrentIndex(panel.metric.findData(key))
        tet_window.viewport.flush()
        assert tet_window.viewport._scalar_title == HEATMAP_METRICS[key][0]


def test_command_line_metrics_are_the_window_s():
    """``kneegui-gui --metric`` offers every heat-map of the window."""
    metric = next(a for a in build_parser()._actions if a.dest == "metric")
    assert tuple(metric.choices) == tuple(HEATMAP_METRICS)


@pytest.fixture(scope="module")
def tet_demo_cache(tmp_path_factory):
    """A cache folder holding the tetrahedral demo leg (``kneegui demo --element-type tet``,
    the smallest: about 166k tets and tri3 skin), as ``kneegui-gui`` generates it."""
    from app.demo import demo_files

    cache = tmp_path_factory.mktemp("tetcache")
    deck, setup = demo_files(2000, cache_dir=cache / "demo", element_type="tet")
    return cache, deck, setup


def test_tet_demo_from_the_command_line_shows_its_tet_heatmap(tmp_path, tet_demo_cache):
    """``kneegui-gui --demo-element-type tet --colour quality`` opens the tetrahedral demo leg
    and, with no ``--metric``, colours it by the first measure it offers: tet collapse."""
    cache, deck, _ = tet_demo_cache
    out = tmp_path / "tet.png"
    env = dict(
        os.environ,
        XDG_CONFIG_HOME=str(tmp_path / "config"),
        KNEEGUI_CACHE_DIR=str(cache),  # the demo generated by the fixture is found there
        KNEEGUI_DATA_DIR=str(tmp_path / "data"),
        QT_API="pyside6",
    )
    demo = ["--demo-elements", "2000", "--demo-element-type", "tet"]
    shot = ["--flexion", "30", "--live", "--colour", "quality", "--screenshot", str(out)]
    proc = subprocess.run(
        [sys.executable, "-m", "app.main", *demo, *shot],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "(quality: tet_collapse, live mapping)" in proc.stdout, proc.stdout
    assert deck == cache / "demo" / "right-2000-tet-sliding" / "demo_leg.k"
    model = read_deck(deck)
    assert len(model.blocks["tet4"]) > 0 and "hex8" not in model.blocks
    assert QImage(str(out)).width() > 800


def test_figures_and_curve_of_a_tet_model_quote_the_tet_collapse(window, qtbot, tet_demo_cache):
    """On a model of tets and triangles (every corner Jacobian 1 by definition) the banner and
    the quality-against-flexion plot give the worst tet collapse instead of the Jacobian."""
    from app.preview import PoseFigures

    _, deck, setup = tet_demo_cache
    ws = window.ws
    window.open_deck(deck, setup)
    wait_idle(qtbot, ws, timeout=300)
    assert window.last_error is None, window.last_error
    window.flexion_panel.slider.setValue(600)
    wait_idle(qtbot, ws, timeout=300)
    q = compute_quality(ws.coords, ws.model.blocks)
    worst = float(q["tet4"].tet_collapse.min())
    figures = ws.view_figures()
    assert figures.worst_tet_collapse == worst < 0.5
    assert not figures.jacobian_says_something
    expected = f"LIVE MAPPING · 60.0° · inverted {q.n_inverted} · "
    qtbot.waitUntil(lambda: window.indicator.text().startswith(expected), timeout=5000)
    text = window.indicator.text()
    assert f"worst tet collapse {worst:.3f}" in text and "Jacobian" not in text
    # the plot: the tet collapse, not the Jacobian, beside the inverted count and volume change
    panel = window.quality_curve_panel
    names = [name for name, _, _ in panel.plotted()]
    assert names == ["worst_tet_collapse", "inverted", "max_volume_change_pct"]
    live_x, live_y, _, _ = panel.series()["worst_tet_collapse"]
    assert len(live_x) == 30 and np.all(np.isfinite(live_y) & (live_y < 1))
    assert live_y[0] > 0  # the first sample, -5 deg, is near the built angle: nothing inverted
    assert live_y[int(np.flatnonzero(live_x == 60.0)[0])] == worst
    window.docks["Quality vs flexion"].raise_()
    qtbot.waitUntil(lambda: panel.isVisible(), timeout=5000)
    assert len(panel.axes) == 3 and all(len(ax.lines) >= 2 for ax in panel.axes)
    # a report's figures the same way (what the banner shows once the export is shown)
    report = {
        "quality": {
            "posed": {"inverted": 0, "jacobian": {"worst": 1.0}, "tet_collapse": {"worst": 0.2}}
        },
        "volume_change": {"max_element_pct": 12.0},
    }
    shown = PoseFigures.from_report(report, ws.model).text()
    assert shown == "inverted 0 · worst tet collapse 0.200 · largest volume change +12.0 %"
