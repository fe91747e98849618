"""``kneegui demo OUTDIR``: write the built-in demo leg (deck + joint setup)."""

from __future__ import annotations

import argparse

from kneegui.demo import write_demo
from kneegui.demo.generator import ELEMENT_TYPES, FLEXION_RANGE_DEG, JOINTS, UNITS

NAME = "demo"
HELP = (
    "Write the built-in demo lower extremity (demo_leg.k and demo_leg.setup.json) to OUTDIR, "
    "so the tool can be tried without a licensed human body model."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("outdir", help="output folder (created if missing)")
    parser.add_argument(
        "--elements",
        type=int,
        default=20_000,
        help="wanted number of solid elements (default 20000; from about 7,200 to over 1000000); "
        "with tetrahedra, the number of grid cells (each tet cell gives 12 tets)",
    )
    parser.add_argument(
        "--side", choices=("right", "left"), default="right", help="which leg (default right)"
    )
    parser.add_argument(
        "--element-type",
        choices=ELEMENT_TYPES,
        default="hex",
        help="solid elements: hex (default), tet (a conforming tetrahedral mesh), mixed "
        "(tetrahedral flesh, hexahedral bones, ligaments, menisci) or tet10 (10-node tets)",
    )
    parser.add_argument(
        "--joint",
        choices=JOINTS,
        default="sliding",
        help="sliding (default: soft tissue on coincident nodes of the bones at the knee) or "
        "welded (one volume of flesh sharing nodes with femur and tibia, filling the joint gap)",
    )
    parser.add_argument(
        "--initial-flexion",
        type=float,
        default=None,
        metavar="DEG",
        help=f"knee angle the leg is built at, {FLEXION_RANGE_DEG[0]:g}-{FLEXION_RANGE_DEG[1]:g} "
        "degrees (default 9)",
    )
    parser.add_argument(
        "--unit",
        choices=tuple(UNITS),
        default="mm",
        help="length unit of the deck and the setup's coordinates (default mm)",
    )


def run(args: argparse.Namespace) -> int:
    deck, setup = write_demo(
        args.outdir,
        elements=args.elements,
        side=args.side,
        element_type=args.element_type,
        joint=args.joint,
        initial_flexion=args.initial_flexion,
        unit=args.unit,
    )
    print(deck)
    print(setup)
    return 0
