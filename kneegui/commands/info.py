"""``kneegui info MODEL``: what is in a deck (counts per type and part, titles, extent, units)."""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from kneegui.io.lsdyna import read_deck
from kneegui.model import Model

NAME = "info"
HELP = "Show element counts per type and part, part titles, bounding box and a units hint."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="LS-DYNA keyword deck (.k/.key/.dyn)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--no-quality", action="store_true", help="skip the mesh-quality summary")


def units_hint(model: Model) -> str:
    """Guess the length unit from the model's extent (a human limb is about 0.5-1 m long)."""
    if model.n_nodes == 0:
        return "unknown"
    extent = float(np.max(np.ptp(model.coords, axis=0)))
    if 100 <= extent <= 5000:
        return "mm"
    if 0.1 <= extent <= 5:
        return "m"
    if 10 <= extent < 100:
        return "cm (or a small model in mm)"
    return "unknown"


def model_info(model: Model) -> dict[str, Any]:
    """The information ``kneegui info`` prints, as a JSON-ready dict."""
    counts = model.element_counts()
    parts = []
    for pid in model.part_ids().tolist():
        p = model.parts.get(pid)
        parts.append(
            {
                "id": pid,
                "title": p.title if p else "",
                "declared": p is not None,
                "elements": counts.get(pid, {}),
            }
        )
    by_type = {etype: len(b) for etype, b in model.blocks.items()}
    src = model.source
    return {
        "files": [str(f.path) for f in src.files] if src is not None else [],
        "nodes": model.n_nodes,
        "elements": model.n_elements,
        "elements_by_type": by_type,
        "parts": parts,
        "node_sets": {str(k): len(v.node_indices) for k, v in model.node_sets.items()},
        "part_sets": {str(k): v.part_ids.tolist() for k, v in model.part_sets.items()},
        "bounding_box": model.bounding_box().tolist(),
        "units_hint": units_hint(model),
        "warnings": list(src.warnings) if src is not None else [],
        "problems": list(getattr(src, "problems", [])) if src is not None else [],
    }


def _quality_summary(model: Model) -> dict[str, Any] | None:
    try:
        from kneegui.quality import compute_quality, summarize_quality
    except ImportError:  # pragma: no cover - quality module is part of the package
        return None
    result = compute_quality(model.coords, model.blocks)
    return summarize_quality(model, result)["model"]


def run(args: argparse.Namespace) -> int:
    # what LS-DYNA would refuse (no nodes or elements, undefined parts, element ids used twice)
    # is listed under "problems" instead of stopping the listing; the exit code is then 2
    model = read_deck(args.model, check_references=False)
    info = model_info(model)
    status = 2 if info["problems"] else 0
    if not args.no_quality and model.n_elements:
        q = _quality_summary(model)
        if q is not None:
            info["quality"] = q
    if args.json:
        print(json.dumps(info, indent=2))
        return status
    print(
        f"files     : {len(info['files'])} ({', '.join(info['files'][:3])}"
        f"{', ...' if len(info['files']) > 3 else ''})"
    )
    print(f"nodes     : {info['nodes']}")
    print(
        f"elements  : {info['elements']}  "
        + "  ".join(f"{k}={v}" for k, v in info["elements_by_type"].items())
    )
    lo, hi = info["bounding_box"]
    print(
        "bbox      : "
        + "  ".join(f"{a}=[{l:.2f}, {h:.2f}]" for a, l, h in zip("xyz", lo, hi, strict=True))
    )
    print(f"units     : {info['units_hint']} (guessed from the extent)")
    print(f"parts     : {len(info['parts'])}")
    for p in info["parts"]:
        counts = " ".join(f"{k}={v}" for k, v in p["elements"].items()) or "no elements"
        flag = "" if p["declared"] else "  (no *PART card)"
        print(f"  {p['id']:>10}  {p['title'][:40]:<40}  {counts}{flag}")
    if "quality" in info:
        print("quality (worst / mean ± std):")
        for metric, s in info["quality"].items():
            if isinstance(s, dict) and "worst" in s:
                print(f"  {metric:<16} {s['worst']:>10.4g}   {s['mean']:.4g} ± {s['std']:.3g}")
            elif metric == "inverted":
                print(f"  inverted elements: {s}")
    for w in info["warnings"]:
        print(f"warning: {w}")
    if info["problems"]:
        print("problems (LS-DYNA refuses this deck; convert and pose stop at the first):")
        for p in info["problems"]:
            print(f"  {p}")
    return status
