"""Plan the files a write creates, so that no write changes a file it should not.

A posed deck with ``*INCLUDE`` files is written as a main file (the path the user named) plus its
includes at the same relative paths beside it. Two posed decks written into one folder would
then share include paths: the second write would silently change the first deck's nodes. The
rules, applied before anything is written:

- two files of one write never go to the same path (an include named like the main output);
- an input file is never a target (unless explicitly allowed);
- the path the user named may be replaced;
- any other existing file is replaced only with ``overwrite`` (the CLI's ``--force``), except
  when it already holds exactly the bytes the write would put there: then it is left untouched
  (a shared include whose nodes did not move is the same file for both decks).

Otherwise :class:`kneegui.errors.OutputConflictError` names every file that would be changed.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path

from kneegui.errors import OutputConflictError


def _key(path: Path) -> str:
    """A path's identity on this file system (absolute, symlinks resolved, case as the OS)."""
    return os.path.normcase(str(Path(path).resolve()))


def check_distinct_targets(targets: Iterable[Path]) -> None:
    """Refuse two outputs of one command that would go to the same file.

    Raises
    ------
    OutputConflictError
        Naming the path given twice.
    """
    seen: dict[str, Path] = {}
    for target in targets:
        key = _key(target)
        if key in seen:
            raise OutputConflictError(
                f"two outputs would be written to the same file ({seen[key]} and {target})",
                target,
            )
        seen[key] = Path(target)


def plan_writes(
    files: Mapping[Path, bytes],
    named: Path | None,
    *,
    inputs: Iterable[Path] = (),
    overwrite: bool = False,
    allow_overwrite_input: bool = False,
) -> dict[Path, bytes]:
    """The files to write out of ``files`` (target path -> bytes), after the checks above.

    Parameters
    ----------
    files : mapping of Path to bytes
        Every file the write would create, the main output included.
    named : Path or None
        The output path the user named (may be replaced).
    inputs : iterable of Path
        The files that were read (never replaced unless ``allow_overwrite_input``).
    overwrite : bool
        Replace other existing files too (``--force``).
    allow_overwrite_input : bool
        Permit a target that is an input file.

    Returns
    -------
    dict of Path to bytes
        ``files`` without the existing files that already hold the same bytes.

    Raises
    ------
    OutputConflictError
        If two targets are one file, a target is an input, or existing files would be changed
        without ``overwrite``. Nothing has been written then.
    """
    check_distinct_targets(files)
    input_keys = {_key(p) for p in inputs}
    named_key = _key(named) if named is not None else None
    todo: dict[Path, bytes] = {}
    clobbered: list[Path] = []
    for target, data in files.items():
        key = _key(target)
        if key in input_keys and not allow_overwrite_input:
            raise OutputConflictError(
                f"refusing to overwrite the input deck {target}; choose another output path",
                target,
            )
        if key != named_key and target.is_file():
            try:
                same = target.stat().st_size == len(data) and target.read_bytes() == data
            except OSError:
                same = False
            if same:
                continue  # already holds these bytes: leave it untouched
            if not overwrite:
                clobbered.append(target)
                continue
        todo[target] = data
    if clobbered:
        names = ", ".join(str(p) for p in clobbered[:3])
        more = f" and {len(clobbered) - 3} more" if len(clobbered) > 3 else ""
        raise OutputConflictError(
            f"would overwrite {len(clobbered)} existing file(s) not named as the output: "
            f"{names}{more} (they may belong to another deck written here); write to an empty "
            "folder, use --flatten for one self-contained file, or --force to overwrite",
            clobbered[0],
        )
    return todo
