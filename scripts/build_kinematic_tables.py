"""Write the shipped kinematic tables in ``resources/kinematics/`` from their published formulas.

Run ``python scripts/build_kinematic_tables.py`` to regenerate them (and print the values quoted
in docs/kinematics.md). Each row carries its source.
"""

from __future__ import annotations

import kneegui.reproducible  # noqa: F401  (before numpy: the same kernels on every machine)

import csv
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.setup.kinematic_tables import (
    SUPPORTED_FLEXION_DEG,
    TABLES_DIR,
    resolve_table,
    shipped_tables,
)

WALKER_SOURCE = (
    "Walker et al. 1988 (in vitro), as quoted in ALGORITHM.md section 2: "
    "i(d) = 0.3695 d - 2.958e-3 d^2 + 7.666e-6 d^3"
)


def walker1988_internal_rotation(flexion_deg: ArrayLike) -> NDArray[np.float64]:
    """Walker et al. 1988 tibial internal rotation (degrees) at knee flexion ``d`` (degrees)."""
    d = np.asarray(flexion_deg, dtype=np.float64)
    return 0.3695 * d - 2.958e-3 * d**2 + 7.666e-6 * d**3


#: Tibial-rotation tables: name -> (value at 120 deg or None for the exact curve, description,
#: source, default flag).
TIBIAL_ROTATION_TABLES = {
    "walker1988": (None, "Walker 1988 exact cubic (15.0 deg at 120 deg)", WALKER_SOURCE, False),
    "walker1988_scaled20": (
        20.0,
        "Walker 1988 shape scaled to 20 deg at 120 deg (between the in-vivo reports)",
        "[OURS] Walker 1988 shape; total between Johal 2005 (20 deg) and Asano 2001 (29.1 deg)",
        True,
    ),
    "asano2001": (
        29.1,
        "Walker 1988 shape scaled to 29.1 deg at 120 deg",
        "Asano et al. 2001 (in vivo, weight-bearing, n=6): 29.1 deg femoral external rotation "
        "from hyperextension to 120 deg; shape Walker 1988",
        False,
    ),
    "johal2005": (
        20.0,
        "Walker 1988 shape scaled to 20 deg at 120 deg",
        "Johal et al. 2005 (in vivo MRI): 20 deg from hyperextension to 120 deg; shape Walker 1988",
        False,
    ),
}

PATELLAR_FLEXION_RATIO = 0.65
PATELLAR_FLEXION_SOURCE = (
    "Review: the patella lags knee flexion by 30-40 %; Li et al. 2007 (in vivo, R^2 = 0.91); "
    "ratio 0.65 [OURS] within that range"
)
PATELLAR_TILT_POINTS = ((0.0, 0.0), (30.0, 8.8), (90.0, 4.6))
PATELLAR_TILT_SOURCE = (
    "von Eisenhart-Rothe et al. 2004 (MRI): tilt opened medially 8.8 deg at "
    "30 deg, 4.6 deg at 90 deg; 0 at 0 and held beyond 90 [OURS]"
)

#: Flexion sampling of the cubic tables, degrees (1-degree steps, interpolation error < 1e-3 deg).
CUBIC_GRID = np.arange(SUPPORTED_FLEXION_DEG[0], SUPPORTED_FLEXION_DEG[1] + 0.5, 1.0)


def _write(path: Path, flexion: NDArray[np.float64], value: NDArray[np.float64], source: str):
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["flexion_deg", "value_deg", "source"])
        for f, v in zip(flexion, value, strict=True):
            w.writerow([f"{f:g}", f"{v:.9f}", source])


def build(outdir: Path = TABLES_DIR) -> list[dict[str, str]]:
    """Write every table and ``index.csv`` into ``outdir``; returns the index rows."""
    outdir.mkdir(parents=True, exist_ok=True)
    index: list[dict[str, str]] = []
    exact = walker1988_internal_rotation(CUBIC_GRID)
    at120 = float(walker1988_internal_rotation(120.0))
    for name, (target120, description, source, default) in TIBIAL_ROTATION_TABLES.items():
        values = exact if target120 is None else exact * (target120 / at120)
        file = f"tibial_rotation_{name}.csv"
        _write(outdir / file, CUBIC_GRID, values, source)
        index.append(
            {
                "quantity": "tibial_rotation",
                "name": name,
                "file": file,
                "default": "yes" if default else "no",
                "description": description,
                "source": source,
            }
        )
    flex = np.array([-30.0, 180.0])
    file = "patellar_flexion_ratio065.csv"
    _write(outdir / file, flex, PATELLAR_FLEXION_RATIO * flex, PATELLAR_FLEXION_SOURCE)
    index.append(
        {
            "quantity": "patellar_flexion",
            "name": "ratio065",
            "file": file,
            "default": "yes",
            "description": "patellar flexion = 0.65 x knee flexion",
            "source": PATELLAR_FLEXION_SOURCE,
        }
    )
    f_tilt = np.array([p[0] for p in PATELLAR_TILT_POINTS])
    v_tilt = np.array([p[1] for p in PATELLAR_TILT_POINTS])
    file = "patellar_tilt_eisenhart2004.csv"
    _write(outdir / file, f_tilt, v_tilt, PATELLAR_TILT_SOURCE)
    index.append(
        {
            "quantity": "patellar_tilt",
            "name": "eisenhart2004",
            "file": file,
            "default": "yes",
            "description": "medial tilt 0 / 8.8 / 4.6 deg at 0 / 30 / 90 deg, held beyond",
            "source": PATELLAR_TILT_SOURCE,
        }
    )
    file = "patellar_tilt_none.csv"
    _write(outdir / file, np.array([0.0, 90.0]), np.zeros(2), "[OURS] no tilt")
    index.append(
        {
            "quantity": "patellar_tilt",
            "name": "none",
            "file": file,
            "default": "no",
            "description": "no patellar tilt",
            "source": "[OURS] no tilt",
        }
    )
    with open(outdir / "index.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(index[0]), lineterminator="\n")
        w.writeheader()
        w.writerows(index)
    return index


def main() -> None:
    """Regenerate the tables and print the values at the usual angles."""
    build()
    shipped_tables.cache_clear()
    angles = [0, 30, 60, 90, 120, 140]
    print("table | " + " | ".join(f"{a} deg" for a in angles))
    for t in shipped_tables():
        table = resolve_table(t.quantity, t.name)
        vals = " | ".join(f"{float(table.value_at(a)):.2f}" for a in angles)
        print(f"{t.quantity}/{t.name} | {vals}")


if __name__ == "__main__":
    main()
