"""``kneegui check``: the pre-flight check of a deck and its setup, before posing."""

from __future__ import annotations

import argparse
import json
import sys

from kneegui.io.lsdyna import read_deck
from kneegui.quality import jsonable
from kneegui.reposition import Repositioner
from kneegui.reposition.preflight import preflight_of
from kneegui.setup import load_setup

NAME = "check"
HELP = (
    "Pre-flight check before posing: elements locked between bones (with the flexion range "
    "over which each stays valid), coincident node pairs (sliding interfaces), the movable "
    "region."
)

#: Rows of the locked-element table in the human summary (--json lists every one).
TABLE_ROWS = 20


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="LS-DYNA keyword deck")
    parser.add_argument("--setup", required=True, help="joint setup JSON (docs/setup-format.md)")
    parser.add_argument(
        "--json", action="store_true", help="print every figure and full list as JSON"
    )
    parser.add_argument(
        "--rows",
        type=int,
        default=TABLE_ROWS,
        metavar="N",
        help=f"locked elements listed in the summary (default {TABLE_ROWS})",
    )


def run(args: argparse.Namespace) -> int:
    model = read_deck(args.model)
    setup = load_setup(args.setup, model)
    preflight = preflight_of(Repositioner(model, setup))
    if args.json:
        json.dump(jsonable(preflight.to_dict()), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        for warning in setup.warnings:
            print(f"kneegui: setup warning: {warning}", file=sys.stderr)
        print("\n".join(preflight.summary_lines(max(args.rows, 0))))
    return 0
