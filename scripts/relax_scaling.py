"""How the relaxation scales: pose one demo size at one angle and print what it did.

``python scripts/relax_scaling.py 200000 90`` prints the precompute, the relaxation's own
precompute and time, its report, and the inverted count and worst Jacobian of the result
(numbers quoted in docs/repositioning.md, "Known limits"); several angles pose one after the
other with the same precompute. ``--deck`` poses the demo as a user gets it: written to an
LS-DYNA deck and read back (coordinates rounded to the deck's fields).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from kneegui.demo import generate_demo_leg, write_demo
from kneegui.io.lsdyna import read_deck
from kneegui.quality import compute_quality
from kneegui.reposition import Repositioner
from kneegui.setup import load_setup
from kneegui.topology import SOLID_TYPES


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("elements", type=int)
    parser.add_argument("flexion", type=float, nargs="+")
    parser.add_argument("--deck", action="store_true", help="write the demo deck and read it back")
    args = parser.parse_args()
    if args.deck:
        with tempfile.TemporaryDirectory() as tmp:
            write_demo(Path(tmp), args.elements)
            model = read_deck(Path(tmp) / "demo_leg.k")
            setup_data = json.loads((Path(tmp) / "demo_leg.setup.json").read_text())
    else:
        leg = generate_demo_leg(args.elements)
        model, setup_data = leg.model, leg.setup
    solids = sum(len(b.ids) for t, b in model.blocks.items() if t in SOLID_TYPES)
    print(f"demo: {solids:,} solids, {model.n_nodes:,} nodes")
    setup = load_setup(setup_data, model)
    t = time.perf_counter()
    rep = Repositioner(model, setup)
    print(f"precompute {time.perf_counter() - t:.2f} s")
    for flexion in args.flexion:
        t = time.perf_counter()
        result = rep.pose_detailed(flexion)
        print(
            f"{flexion:g} deg: pose_detailed {time.perf_counter() - t:.2f} s "
            f"(relaxation precompute {rep.timings_s['relaxation']:.2f} s)"
        )
        print(result.relaxation.to_dict())
        q = compute_quality(result.coords, model.blocks)
        print(
            f"{flexion:g} deg: inverted {q.n_inverted}, worst corner Jacobian "
            f"{q.worst_jacobian():.4f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
