"""The desktop application (PySide6 + pyvistaqt) over the engine."""

import kneegui.reproducible  # noqa: F401  (before numpy: the same kernels on every machine)
