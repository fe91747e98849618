"""``kneegui convert MODEL --out PATH``: write a deck as LS-DYNA (lossless), Abaqus or VTU."""

from __future__ import annotations

import argparse
from pathlib import Path

from kneegui.errors import DeckError
from kneegui.io.lsdyna import read_deck, write_deck

NAME = "convert"
HELP = "Write a deck losslessly (LS-DYNA, optionally flattened) or export it to Abaqus or VTU."

_SUFFIX_FORMATS = {
    ".inp": "abaqus",
    ".vtu": "vtu",
    ".k": "lsdyna",
    ".key": "lsdyna",
    ".dyn": "lsdyna",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="LS-DYNA keyword deck")
    parser.add_argument("--out", required=True, help="output file")
    parser.add_argument(
        "--format",
        choices=("lsdyna", "abaqus", "vtu"),
        help="output format (default: from the --out suffix, else lsdyna)",
    )
    parser.add_argument(
        "--flatten", action="store_true", help="LS-DYNA: inline every *INCLUDE into one file"
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="LS-DYNA: overwrite existing include files beside --out (another deck's, maybe)",
    )


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    fmt = args.format or _SUFFIX_FORMATS.get(out.suffix.lower(), "lsdyna")
    if args.flatten and fmt != "lsdyna":
        raise DeckError("--flatten applies to LS-DYNA output only")
    model = read_deck(args.model)
    if fmt == "lsdyna":
        written = write_deck(model, out, flatten=args.flatten, overwrite=args.force)
    elif fmt == "abaqus":
        from kneegui.io.abaqus import write_abaqus

        written = [write_abaqus(model, out, heading=f"kneegui convert {args.model}")]
    else:
        from kneegui.io.vtu import write_vtu

        written = [write_vtu(model, out)]
    for path in written:
        print(path)
    return 0
