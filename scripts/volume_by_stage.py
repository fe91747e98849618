"""Where the soft tissue's volume change comes from: its 95th percentile after each stage.

``python scripts/volume_by_stage.py DECK [--setup SETUP] [--restore-volume] 90 [120 ...]``
(a deck and setup as ``kneegui demo`` writes them) prints, per angle, the 95th percentile of
the soft solids' |volume change| and how many change by more than 25 %: after the mapping,
after each stage of the export that another follows (``pose_model``'s ``stage_done``: the
first untangled round, the untangling, the quality stage) and as exported, with the time.
docs/repositioning.md (known limits, "Where the fine meshes' volume change comes from")
quotes it.
"""

from __future__ import annotations

import kneegui.reproducible  # noqa: F401  (before numpy: the same kernels on every machine)

import argparse
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from kneegui.io.lsdyna import read_deck
from kneegui.meshopt.volume_correction import VolumeCorrectionOptions
from kneegui.model import Model
from kneegui.quality.metrics import compute_quality
from kneegui.quality.volume import volume_change_pct
from kneegui.reposition import Repositioner, RepositionOptions
from kneegui.reposition.pipeline import pose_model
from kneegui.reposition.repositioner import SOFT_ROLES
from kneegui.setup import JointSetup, load_setup
from kneegui.topology import SOLID_TYPES


class SoftVolumeChange:
    """The soft solids' |volume change| (percent) against the deck's initial pose."""

    def __init__(self, model: Model, setup: JointSetup) -> None:
        soft = list(setup.parts_of(*SOFT_ROLES))
        self.model = model
        self.rows = {
            etype: np.flatnonzero(np.isin(block.part_ids, soft))
            for etype, block in model.blocks.items()
            if etype in SOLID_TYPES
        }
        self.initial = self._volumes(model.coords)

    def _volumes(self, coords: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
        q = compute_quality(coords, self.model.blocks, rows=self.rows)
        return {etype: q[etype].volume for etype in self.rows if etype in q}

    def __call__(self, coords: NDArray[np.float64]) -> str:
        now = self._volumes(coords)
        change = np.concatenate(
            [np.abs(volume_change_pct(now[etype], self.initial[etype])) for etype in now]
        )
        over = int(np.count_nonzero(change > 25.0))
        return f"p95 {np.percentile(change, 95):6.2f} %, {over:,} of {len(change):,} over 25 %"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("deck", type=Path)
    parser.add_argument("angles", type=float, nargs="+")
    parser.add_argument("--setup", type=Path, help="default: DECK with .setup.json")
    parser.add_argument(
        "--restore-volume", action="store_true", help="the opt-in volume step (kneegui pose)"
    )
    args = parser.parse_args()
    setup_path = args.setup or args.deck.with_suffix(".setup.json")
    model = read_deck(args.deck)
    setup = load_setup(setup_path, model)
    options = RepositionOptions(
        volume_correction=VolumeCorrectionOptions() if args.restore_volume else None
    )
    repositioner = Repositioner(model, setup, options)
    measure = SoftVolumeChange(model, setup)
    for angle in args.angles:
        print(f"{angle:g} deg: mapping                  {measure(repositioner.pose(angle))}")
        start = time.perf_counter()

        def stage_done(
            stage: str, coords: NDArray[np.float64], angle: float = angle, start: float = start
        ) -> None:
            elapsed = time.perf_counter() - start
            print(f"{angle:g} deg: after {stage:<12} {elapsed:6.1f} s {measure(coords)}")

        posed = pose_model(repositioner, angle, stage_done=stage_done)
        elapsed = time.perf_counter() - start
        print(f"{angle:g} deg: exported {elapsed:17.1f} s {measure(posed.model.coords)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
