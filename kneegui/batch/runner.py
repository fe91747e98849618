"""Run a batch plan: every posture in worker processes, here or on a Dask cluster.

:func:`run_plan` fingerprints the inputs, skips (with ``resume``) the postures whose outputs are
complete, hands the rest to a backend and records every result in ``OUT/manifest.json``
(rewritten atomically after each posture), then writes the summary table and plots.

Backends:

- local (default): ``workers`` single-process :class:`~concurrent.futures.ProcessPoolExecutor`
  slots (spawned, single-threaded math). Each slot poses one posture at a time and is given the
  next posture of the deck it last posed, so it precomputes each deck once. A slot whose process
  dies (killed, out of memory) fails only the posture it was posing; a new process takes its
  place and the plan goes on.
- Dask: ``distributed.Client(scheduler)`` on an existing cluster; one task per posture, the same
  worker function and cache. Dask retries a task whose worker died on another worker and gives
  up with ``KilledWorker``, which fails that posture only.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import time
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from kneegui import __version__
from kneegui.batch.plan import Plan
from kneegui.batch.summary import summary_row, write_plots, write_summary
from kneegui.batch.worker import (
    SINGLE_THREAD_ENV,
    STATUS_ERROR,
    STATUS_GATE_FAILED,
    STATUS_OK,
    PostureResult,
    PostureTask,
    file_sha256,
    init_worker,
    run_posture,
)
from kneegui.errors import KneeguiError
from kneegui.io.atomic import atomic_write_text

MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = "kneegui-batch-manifest"


class BatchError(KneeguiError):
    """A batch cannot start (output folder already used, Dask not installed or unreachable)."""


@dataclass
class BatchProgress:
    """Counts passed to the progress callback after every posture.

    ``eta_s`` is None until a posture has finished in this run.
    """

    total: int
    done: int = 0
    failed: int = 0
    skipped: int = 0
    elapsed_s: float = 0.0
    eta_s: float | None = None
    last: str = ""

    @property
    def remaining(self) -> int:
        return self.total - self.done - self.failed


@dataclass
class BatchOutcome:
    """What :func:`run_plan` did: counts and the files it wrote."""

    ok: int = 0
    gate_failed: int = 0
    errors: int = 0
    skipped: int = 0
    seconds: float = 0.0
    files: list[Path] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


ProgressCallback = Callable[[BatchProgress], None]


# ---------------------------------------------------------------------------- fingerprints
def _table_digest(choice: str) -> str:
    return file_sha256(choice) if os.path.isabs(choice) and os.path.isfile(choice) else choice


def make_tasks(plan: Plan) -> list[PostureTask]:
    """One task per posture with the fingerprints of its inputs (each file hashed once)."""
    digests: dict[Path, str] = {}

    def digest(path: Path) -> str:
        if path not in digests:
            digests[path] = file_sha256(path)
        return digests[path]

    tasks = []
    for p in plan.postures:
        pre = {
            "deck": [str(p.deck), digest(p.deck)],
            "setup": [str(p.setup), digest(p.setup)],
            "kinematics": [[q, c, _table_digest(c)] for q, c in p.kinematics],
            "relax": p.options.relax,
            "method": p.options.method,
            "restore_volume": p.options.restore_volume,
            "kneegui": __version__,
        }
        inputs = dict(pre, flexion=p.flexion, options=asdict(p.options), posture=p.id)
        tasks.append(
            PostureTask(
                posture=p,
                inputs=_sha(inputs),
                precompute_key=_sha(pre),
            )
        )
    return tasks


def _sha(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()


# ---------------------------------------------------------------------------- resume
def completed_report(task: PostureTask) -> dict[str, Any] | None:
    """The report of a posture whose outputs are complete and valid for these inputs, or None.

    Complete and valid: the report parses, names this posture and these inputs, every file it
    lists has the sha256 recorded, and the deck reads back with kneegui's reader.
    """
    from kneegui.io.lsdyna import read_deck

    p = task.posture
    try:
        report = json.loads(p.report_out.read_text(encoding="utf-8"))
        batch = report["batch"]
        if batch["posture"] != p.id or batch["inputs"] != task.inputs:
            return None
        for name, sha in batch["files"].items():
            if file_sha256(p.folder / name) != sha:
                return None
        if report["written"]:
            read_deck(p.deck_out)
        elif p.options.force or report["gate"]["passed"]:
            return None  # a deck should have been written
    except (OSError, ValueError, KeyError, TypeError, KneeguiError):
        return None
    return report


# ---------------------------------------------------------------------------- manifest
def _entry(task: PostureTask, out: Path) -> dict[str, Any]:
    p = task.posture
    return {
        "id": p.id,
        "deck": p.deck_name,
        "tables": p.tables_tag,
        "flexion": p.flexion,
        "input": str(p.deck),
        "status": "pending",
        "reason": "",
        "skipped": False,
        "seconds": None,
        "deck_out": str(p.deck_out.relative_to(out)),
        "report": str(p.report_out.relative_to(out)),
        "row": None,
    }


def _write_manifest(plan: Plan, entries: dict[str, dict[str, Any]]) -> Path:
    data = {
        "format": MANIFEST_FORMAT,
        "plan": str(plan.path.resolve()),
        "kneegui": __version__,
        "postures": list(entries.values()),
    }
    return atomic_write_text(plan.out / MANIFEST_NAME, json.dumps(data, indent=2) + "\n")


# ---------------------------------------------------------------------------- backends
@contextmanager
def _single_thread_env() -> Iterator[None]:
    """Start worker processes with :data:`SINGLE_THREAD_ENV` (their math libraries read it at
    import, before any initializer could set it)."""
    saved = {k: os.environ.get(k) for k in SINGLE_THREAD_ENV}
    os.environ.update(SINGLE_THREAD_ENV)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class _Slot:
    """One worker process (a one-process pool) with the posture it is posing."""

    def __init__(self) -> None:
        self.executor = self._new()
        self.future: Future[PostureResult] | None = None
        self.task: PostureTask | None = None
        self.started = 0.0
        self.last_key: str | None = None

    @staticmethod
    def _new() -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            1, mp_context=multiprocessing.get_context("spawn"), initializer=init_worker
        )

    def submit(self, task: PostureTask) -> None:
        for attempt in range(2):
            try:
                with _single_thread_env():  # the process is spawned by its first submit
                    self.future = self.executor.submit(run_posture, task)
                break
            except BrokenProcessPool:  # died while idle: nothing was lost, start another
                if attempt:
                    raise
                self.restart()
        self.task, self.started, self.last_key = task, time.perf_counter(), task.precompute_key

    def restart(self) -> None:
        self.executor.shutdown(wait=False, cancel_futures=True)
        self.executor = self._new()
        self.last_key = None


def _take(pending: list[PostureTask], key: str | None, busy: set[str]) -> PostureTask:
    """The next posture for a slot: the next of the deck it last posed, else the first of a deck
    no other slot is posing, else the first (so each worker precomputes as few decks as it can)."""
    for wanted in (lambda t: t.precompute_key == key, lambda t: t.precompute_key not in busy):
        for i, task in enumerate(pending):
            if wanted(task):
                return pending.pop(i)
    return pending.pop(0)


def _failed(task: PostureTask, reason: str, seconds: float) -> PostureResult:
    return PostureResult(task.posture.id, STATUS_ERROR, reason, None, seconds)


def _run_local(
    tasks: list[PostureTask], workers: int, on_result: Callable[[PostureResult], None]
) -> None:
    pending = list(tasks)
    slots = [_Slot() for _ in range(max(1, min(workers, len(tasks))))]
    try:
        while pending or any(s.future for s in slots):
            for slot in slots:
                if slot.future is None and pending:
                    busy = {s.task.precompute_key for s in slots if s.task is not None}
                    slot.submit(_take(pending, slot.last_key, busy))
            running = [s.future for s in slots if s.future is not None]
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for slot in slots:
                if slot.future is None or slot.future not in done:
                    continue
                task, seconds = slot.task, time.perf_counter() - slot.started
                assert task is not None
                try:
                    result = slot.future.result()
                except BrokenProcessPool:
                    result = _failed(
                        task,
                        "the worker process died while posing it (killed, out of memory or "
                        "crashed)",
                        seconds,
                    )
                    slot.restart()
                except Exception as exc:  # e.g. a result that could not be sent back
                    result = _failed(task, f"{type(exc).__name__}: {exc}", seconds)
                slot.future = slot.task = None
                on_result(result)
    finally:
        # all idle after a normal end; after an interrupt do not wait for running postures
        finished = not pending and all(s.future is None for s in slots)
        for slot in slots:
            slot.executor.shutdown(wait=finished, cancel_futures=True)


def _connect(scheduler: str) -> Any:
    """A ``distributed.Client`` on the running scheduler (before anything is written)."""
    try:
        from distributed import Client
    except ImportError:
        raise BatchError(
            "--scheduler needs Dask: pip install 'kneegui[batch]' (dask[distributed])"
        ) from None
    try:
        return Client(scheduler, timeout="20s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise BatchError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None


def _run_dask(
    client: Any, tasks: list[PostureTask], on_result: Callable[[PostureResult], None]
) -> None:
    from distributed import as_completed

    started = time.perf_counter()
    run_id = uuid.uuid4().hex[:12]  # keys unique to this run: no result of another is reused
    futures = {
        client.submit(run_posture, task, pure=False, key=f"kneegui-{run_id}-{i}"): task
        for i, task in enumerate(tasks)
    }
    for future in as_completed(futures):
        task = futures[future]
        try:
            result = future.result()
        except Exception as exc:  # KilledWorker: its workers died posing it
            result = _failed(task, f"{type(exc).__name__}: {exc}", time.perf_counter() - started)
        on_result(result)


# ---------------------------------------------------------------------------- driver
def run_plan(
    plan: Plan,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
    progress: ProgressCallback | None = None,
) -> BatchOutcome:
    """Pose every posture of a plan; record, summarise and plot the results.

    Parameters
    ----------
    plan : Plan
        From :func:`kneegui.batch.plan.load_plan`.
    workers : int, optional
        Local worker processes (default: the CPU count). Ignored with ``scheduler``.
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://host:port``); the decks must be readable
        at the same paths on its workers.
    resume : bool
        Skip the postures whose outputs are complete and valid for the same inputs. Without
        it, an output folder that already holds a manifest is refused.
    progress : callable, optional
        Called with a :class:`BatchProgress` after every posture.

    Returns
    -------
    BatchOutcome

    Raises
    ------
    BatchError
        The output holds an earlier run and ``resume`` is not set, or Dask is missing or
        unreachable. A failing posture never raises: it is recorded and the others go on.
    """
    t0 = time.perf_counter()
    manifest = plan.out / MANIFEST_NAME
    if manifest.exists() and not resume:
        raise BatchError(
            f"{plan.out} already holds a batch run ({MANIFEST_NAME}); use --resume to complete "
            "it, or choose another output folder"
        )
    client = _connect(scheduler) if scheduler else None
    try:
        return _run(plan, client, workers, resume, progress, t0)
    finally:
        if client is not None:
            client.close()


def _run(
    plan: Plan,
    client: Any,
    workers: int | None,
    resume: bool,
    progress: ProgressCallback | None,
    t0: float,
) -> BatchOutcome:
    tasks = make_tasks(plan)
    entries = {t.posture.id: _entry(t, plan.out) for t in tasks}
    state = BatchProgress(total=len(tasks))
    outcome = BatchOutcome()
    todo = []
    for task in tasks:
        report = completed_report(task) if resume else None
        if report is None:
            todo.append(task)
            continue
        passed = report["gate"]["passed"]
        entries[task.posture.id].update(
            status=STATUS_OK if passed else STATUS_GATE_FAILED,
            reason="; ".join(report["gate"]["reasons"]),
            skipped=True,
            row=summary_row(task.posture, report),
        )
        state.done += 1
        state.skipped += 1
    plan.out.mkdir(parents=True, exist_ok=True)
    _write_manifest(plan, entries)
    if progress:
        progress(state)
    finished_here = 0
    todo_by_id = {t.posture.id: t for t in todo}

    def on_result(result: PostureResult) -> None:
        nonlocal finished_here
        entry = entries[result.id]
        task = todo_by_id[result.id]
        entry.update(
            status=result.status,
            reason=result.reason,
            skipped=False,
            seconds=result.seconds,
            row=None if result.report is None else summary_row(task.posture, result.report),
        )
        _write_manifest(plan, entries)
        finished_here += 1
        if result.status == STATUS_ERROR:
            state.failed += 1
        else:
            state.done += 1
        state.elapsed_s = time.perf_counter() - t0
        state.eta_s = state.elapsed_s / finished_here * state.remaining
        state.last = f"{result.id}: {result.status}"
        if progress:
            progress(state)

    if todo:
        if client is not None:
            _run_dask(client, todo, on_result)
        else:
            _run_local(todo, workers or os.cpu_count() or 1, on_result)
    rows = list(entries.values())
    outcome.files.append(_write_manifest(plan, entries))
    outcome.files += write_summary(plan.out, rows)
    plots, warnings = write_plots(plan.out, rows)
    outcome.files += plots
    outcome.warnings += warnings
    for e in rows:
        if e["status"] == STATUS_OK:
            outcome.ok += 1
        elif e["status"] == STATUS_GATE_FAILED:
            outcome.gate_failed += 1
        else:
            outcome.errors += 1
    outcome.skipped = state.skipped
    outcome.seconds = time.perf_counter() - t0
    return outcome
