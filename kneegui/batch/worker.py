"""The worker side of a batch: pose one posture, reusing the deck's precompute across angles.

:func:`run_posture` runs in a worker process (a local process pool's or a Dask worker's). The
:class:`~kneegui.reposition.Repositioner` it builds is kept in a module-level cache keyed by what
the precompute depends on (deck and setup files with their digests, table choices, options), so a
worker that poses several angles of one deck reads the deck and precomputes once. The cache holds
one entry: a whole-body repositioner is large, and the runners hand a worker its deck's postures
one after another.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from kneegui.batch.plan import Posture
from kneegui.errors import KneeguiError
from kneegui.reposition.pipeline import export_pose

#: Environment every worker process is started with: one thread per math library, so that a
#: posture's bytes never depend on the machine's core count or on the scheduler used (Dask's
#: nanny sets the same three by default).
SINGLE_THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}

STATUS_OK, STATUS_GATE_FAILED, STATUS_ERROR = "ok", "gate-failed", "error"


@dataclass(frozen=True)
class PostureTask:
    """A posture with the fingerprint of its inputs (computed once by the runner).

    Attributes
    ----------
    posture : Posture
    inputs : str
        sha256 over the deck and setup bytes, table choices, options, angle and kneegui version;
        stored in the report so that ``--resume`` knows the outputs belong to these inputs.
    precompute_key : str
        sha256 over what the precompute depends on (the same without the angle and the
        export options): the worker's cache key.
    """

    posture: Posture
    inputs: str
    precompute_key: str


@dataclass(frozen=True)
class PostureResult:
    """What became of one posture.

    Attributes
    ----------
    id : str
        The posture's id (its output folder relative to the plan's output).
    status : str
        ``"ok"``, ``"gate-failed"`` (the deck is written only with ``force``) or ``"error"``.
    reason : str
        Why it failed (gate reasons or the error), empty when ok.
    report : dict or None
        The pose report as written (None on error).
    seconds : float
        Wall time in the worker (or until the failure was seen).
    """

    id: str
    status: str
    reason: str
    report: dict[str, Any] | None
    seconds: float


_cache: dict[str, Any] = {}
_cache_lock = threading.Lock()


def init_worker() -> None:
    """Process-pool initializer: single-threaded math libraries (see :data:`SINGLE_THREAD_ENV`)."""
    os.environ.update(SINGLE_THREAD_ENV)


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _repositioner(task: PostureTask) -> tuple[Any, dict[str, float], bool]:
    """The posture's repositioner: from the cache, or read, set up and precomputed now."""
    from kneegui.io.lsdyna import read_deck
    from kneegui.meshopt.volume_correction import VolumeCorrectionOptions
    from kneegui.reposition import Repositioner, RepositionOptions
    from kneegui.setup import load_setup

    p = task.posture
    key = task.precompute_key
    if _cache.get("key") == key:
        return _cache["repositioner"], _cache["timings"], True
    _cache.clear()  # free the previous deck before reading the next
    t = time.perf_counter()
    model = read_deck(p.deck)
    t_read = time.perf_counter() - t
    t = time.perf_counter()
    setup = load_setup(p.setup, model)
    if p.kinematics:
        data = setup.to_dict()
        data["kinematics"].update(dict(p.kinematics))
        setup = load_setup(data, model)
    opts: dict = {"relax": p.options.relax}
    if p.options.method:
        opts["method"] = p.options.method
    if p.options.restore_volume:
        opts["volume_correction"] = VolumeCorrectionOptions()
    t_setup = time.perf_counter() - t
    t = time.perf_counter()
    repositioner = Repositioner(model, setup, RepositionOptions(**opts))
    t_pre = time.perf_counter() - t
    timings = {
        "read": t_read,
        "setup": t_setup,
        "precompute": t_pre,
        **{f"precompute_{k}": v for k, v in repositioner.timings_s.items()},
    }
    _cache.update(key=key, repositioner=repositioner, timings=timings)
    return repositioner, timings, False


def _export_posture(repositioner: Any, posture: Posture, context_timings: dict[str, float]) -> Any:
    """The one place a batch poses and writes a deck: ``kneegui pose``'s own export step.

    Returns the :class:`~kneegui.reposition.pipeline.PosedModel` whose report lists the files
    written (none when the gate fails without ``force``).
    """
    return export_pose(
        repositioner,
        posture.flexion,
        posture.deck_out,
        model_path=posture.deck,
        smooth=posture.options.smooth,
        force=posture.options.force,
        flatten=posture.options.flatten,
        # the posture's folder is its own (the plan refuses two postures sharing a path): what
        # is there is an earlier, interrupted write of this same posture
        overwrite=True,
        context_timings=context_timings,
    )


def run_posture(task: PostureTask) -> PostureResult:
    """Pose one posture and write its deck and report (atomically); never raises for a bad input.

    The report is the ``kneegui pose`` report plus a ``batch`` section: the posture id, the
    inputs' fingerprint, the sha256 of every file written (relative to the posture folder), and
    whether the precompute was reused. It is written after the deck, so a report that lists a
    file proves the file was complete.
    """
    from kneegui.io.atomic import atomic_write_text

    p = task.posture
    t0 = time.perf_counter()
    try:
        with _cache_lock:  # one posture at a time per process (Dask workers may have threads)
            repositioner, timings, reused = _repositioner(task)
            posed = _export_posture(repositioner, p, timings)
        report = posed.report
        report["batch"] = {
            "posture": p.id,
            "inputs": task.inputs,
            "precompute_reused": reused,
            "files": {os.path.relpath(f, p.folder): file_sha256(f) for f in report["written"]},
        }
        atomic_write_text(p.report_out, json.dumps(report, indent=2) + "\n")
    except (KneeguiError, OSError, MemoryError, ValueError) as exc:
        return PostureResult(
            p.id, STATUS_ERROR, f"{type(exc).__name__}: {exc}", None, time.perf_counter() - t0
        )
    except Exception as exc:  # a bug must not stop the family: record it with its place
        where = traceback.extract_tb(exc.__traceback__)[-1]
        return PostureResult(
            p.id,
            STATUS_ERROR,
            f"{type(exc).__name__}: {exc} ({Path(where.filename).name}:{where.lineno})",
            None,
            time.perf_counter() - t0,
        )
    status = STATUS_OK if posed.passes_gate else STATUS_GATE_FAILED
    return PostureResult(
        p.id, status, "; ".join(posed.gate_reasons), report, time.perf_counter() - t0
    )
