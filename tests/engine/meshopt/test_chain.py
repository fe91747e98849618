"""The mesh-improvement chain: its stages run once each, in order, and ``None`` skips one."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.meshopt import (
    ImprovementOptions,
    QualityOptions,
    RelaxOptions,
    RelaxReport,
    SmoothingReport,
    SmoothOptions,
    improve_region,
)
from kneegui.meshopt.quality_optimiser import QualityOptimisationReport


class Region:
    """Records what the chain asks for; each stage adds its number to every coordinate."""

    def __init__(self, untangled: bool = True):
        self.calls: list[str] = []
        self.untangled = untangled
        self.fractions: list[float] = []

    def progress(self, fraction, message):
        self.fractions.append(fraction)

    def untangle(self, coords, options, stop_when_untangled, progress, cancel, untangled=None):
        assert isinstance(options, RelaxOptions)
        self.calls.append(f"untangle(stop={stop_when_untangled})")
        if untangled is not None and self.untangled:
            pose = coords + 0.5  # the first untangled round's pose, before the last rounds
            untangled(pose)
            pose[:] = -100.0  # the region's own copy: what the callee saw must not change
        progress(1.0, "untangled")
        report = RelaxReport(
            free_nodes=3,
            min_det_after=0.5 if self.untangled else -1.0,
            inverted_corners_after=0 if self.untangled else 2,
        )
        return coords + 1.0, report, self.untangled

    def optimise(self, coords, options, progress, cancel):
        assert isinstance(options, QualityOptions)
        self.calls.append("optimise")
        return coords + 2.0, QualityOptimisationReport(free_nodes=3)

    def smooth(self, coords, options, progress, cancel):
        assert isinstance(options, SmoothOptions)
        self.calls.append("smooth")
        progress(0.5, "smoothing")
        return coords + 4.0, SmoothingReport(
            free_nodes=1, sliding_nodes=0, moved_nodes=1, stage1_sweeps=0, stage1_moves=0,
            stage2_nodes=0, stage2_improved=0, worst_jacobian_before=0.1,
            worst_jacobian_after=0.2, inverted_before=0, inverted_after=0,
            max_displacement=4.0, seconds=0.0,
        )  # fmt: skip


def test_the_stages_run_in_order_and_the_input_is_untouched():
    coords = np.zeros((2, 3))
    region = Region()
    out, report = improve_region(coords, region, ImprovementOptions(), region.progress)
    assert region.calls == ["untangle(stop=True)", "optimise", "smooth"]
    np.testing.assert_array_equal(out, 7.0)
    np.testing.assert_array_equal(report.relaxed, 3.0)  # before the smoothing
    np.testing.assert_array_equal(coords, 0.0)
    assert report.relaxation.quality.free_nodes == 3 and report.smoothing.moved_nodes == 1
    assert region.fractions == sorted(region.fractions) and region.fractions[-1] == 1.0


@pytest.mark.parametrize(
    ("options", "calls", "value"),
    [
        (ImprovementOptions(smooth=None), ["untangle(stop=True)", "optimise"], 3.0),
        (ImprovementOptions(quality=None), ["untangle(stop=False)", "smooth"], 5.0),
        (ImprovementOptions(relax=None), ["smooth"], 4.0),
    ],
)
def test_a_stage_set_to_none_does_not_run(options, calls, value):
    region = Region()
    out, report = improve_region(np.zeros((2, 3)), region, options)
    assert region.calls == calls
    np.testing.assert_array_equal(out, value)
    assert (report.relaxation is None) == (options.relax is None)
    assert (report.smoothing is None) == (options.smooth is None)


def test_the_quality_stage_runs_around_what_the_untangling_left_inverted():
    """By default the quality stage follows a region left with corners inverted (the region
    holds their nodes); with ``hold_inverted=False`` it waits for an untangled region."""
    region = Region(untangled=False)
    _, report = improve_region(np.zeros((2, 3)), region, ImprovementOptions(smooth=None))
    assert region.calls == ["untangle(stop=True)", "optimise"]
    assert report.relaxation.quality is not None
    region = Region(untangled=False)
    waiting = ImprovementOptions(smooth=None, quality=QualityOptions(hold_inverted=False))
    _, report = improve_region(np.zeros((2, 3)), region, waiting)
    assert region.calls == ["untangle(stop=True)"] and report.relaxation.quality is None


def test_a_region_with_nothing_to_untangle_is_not_optimised_for_being_stuck():
    """No region at all (untangle says no, nothing inverted): no quality stage."""

    class Empty(Region):
        def untangle(self, coords, options, stop_when_untangled, progress, cancel, untangled=None):
            self.calls.append("untangle")
            return coords, RelaxReport(), False

    region = Empty()
    improve_region(np.zeros((2, 3)), region, ImprovementOptions(smooth=None))
    assert region.calls == ["untangle"]


def test_without_a_quality_stage_a_region_left_inverted_goes_on_to_the_smoothing():
    """``quality=None`` skips the stage even when the untangling leaves corners inverted (it
    raised AttributeError there: the stage's options were read before asking whether it runs)."""
    region = Region(untangled=False)
    out, report = improve_region(np.zeros((2, 3)), region, ImprovementOptions(quality=None))
    assert region.calls == ["untangle(stop=False)", "smooth"]
    assert report.relaxation.inverted_corners_after == 2 and report.relaxation.quality is None
    np.testing.assert_array_equal(out, 5.0)


@pytest.mark.parametrize(
    ("options", "stages"),
    [
        # the first untangled pose (0.5), then each stage's end that another stage follows
        (ImprovementOptions(), [("untangle", 0.5), ("untangle", 1.0), ("quality", 3.0)]),
        (ImprovementOptions(smooth=None), [("untangle", 0.5), ("untangle", 1.0)]),
        (ImprovementOptions(quality=None), [("untangle", 0.5), ("untangle", 1.0)]),
        # nothing follows the untangling: no call at all
        (ImprovementOptions(quality=None, smooth=None), []),
        (ImprovementOptions(relax=None), []),
    ],
)
def test_each_stage_that_another_follows_hands_over_its_pose(options, stages):
    """``stage_done`` sees the whole pose after each stage another stage follows, as a copy:
    what the callee does with it cannot change the result."""
    seen = []

    def stage_done(stage, x):
        seen.append((stage, float(x[0, 0])))
        x[:] = -100.0  # the callee's copy

    plain, _ = improve_region(np.zeros((2, 3)), Region(), options)
    out, _ = improve_region(np.zeros((2, 3)), Region(), options, stage_done=stage_done)
    assert seen == stages
    np.testing.assert_array_equal(out, plain)
