"""``kneegui demo OUTDIR``: write the built-in demo leg (deck + joint setup)."""

from __future__ import annotations

import argparse

from kneegui.demo import write_demo

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
        help="wanted number of solid elements (default 20000; from about 7,200 to over 1000000)",
    )
    parser.add_argument(
        "--side", choices=("right", "left"), default="right", help="which leg (default right)"
    )


def run(args: argparse.Namespace) -> int:
    deck, setup = write_demo(args.outdir, elements=args.elements, side=args.side)
    print(deck)
    print(setup)
    return 0
