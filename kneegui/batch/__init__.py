"""Posture families in batch: many decks x many angles x kinematic tables (docs/batch.md).

- :func:`load_plan` reads and validates a TOML plan into postures (:mod:`kneegui.batch.plan`).
- :func:`run_plan` poses them in local worker processes or on a Dask cluster, records each in a
  manifest, resumes, and writes the summary and plots (:mod:`kneegui.batch.runner`).
"""

from kneegui.batch.plan import Plan, Posture, PostureOptions, load_plan
from kneegui.batch.runner import BatchError, BatchOutcome, BatchProgress, run_plan

__all__ = [
    "BatchError",
    "BatchOutcome",
    "BatchProgress",
    "Plan",
    "Posture",
    "PostureOptions",
    "load_plan",
    "run_plan",
]
