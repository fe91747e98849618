"""kneegui engine: read a human-body FE model, re-pose its knee, check and smooth the mesh.

The engine uses numpy and scipy only; it never imports Qt, VTK or pyvista (the GUI lives in
``app``).
"""

# first, before numpy is loaded: the same kernels on every x86-64 machine
import kneegui.reproducible  # noqa: F401

from kneegui.errors import DeckError, GeometryError, KneeguiError, SetupError
from kneegui.model import ElementBlock, Model, Part
from kneegui.topology import ELEMENT_TYPES

__all__ = [
    "ELEMENT_TYPES",
    "DeckError",
    "ElementBlock",
    "GeometryError",
    "KneeguiError",
    "Model",
    "Part",
    "SetupError",
]
__version__ = "0.1.0"
