"""Work-arounds for Qt binding defects the window would otherwise crash on.

PySide6 6.12.0 drops one reference to ``None`` on every call of a method that returns nothing
(``processEvents``, ``QTimer.start``, ``QSignalBlocker.__exit__``...) and to ``True``/``False`` in
some signal paths. On Python < 3.12, where these singletons are not immortal, their count reaches
zero after some tens of thousands of calls and the interpreter aborts ("none_dealloc: deallocating
None"). PySide6 6.11.3 does not have the defect: pin ``PySide6-Essentials<6.12`` where possible.
When the defective version is loaded anyway, :func:`protect_singletons` gives the three
singletons a very large reference count once, which makes them effectively immortal, as Python
3.12 does.
"""

from __future__ import annotations

import ctypes
import sys

DEFECTIVE_PYSIDE = ("6.12.0",)
_EXTRA_REFERENCES = 1 << 40
_done = False


def pyside_is_defective() -> bool:
    """Whether the loaded PySide6 leaks singleton references (and Python would crash on it)."""
    import PySide6

    return PySide6.__version__ in DEFECTIVE_PYSIDE and sys.version_info < (3, 12)


def protect_singletons() -> bool:
    """Make ``None``, ``True`` and ``False`` effectively immortal when needed (idempotent).

    Returns True when the work-around was applied.
    """
    global _done
    if _done or not pyside_is_defective():
        return False
    for obj in (None, True, False):
        count = ctypes.c_ssize_t.from_address(id(obj))  # ob_refcnt is the first field
        count.value += _EXTRA_REFERENCES
    _done = True
    return True
