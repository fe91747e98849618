"""House rule 1: the engine never imports Qt, VTK or pyvista.

The run-time half of the check: importing every engine module loads no GUI module, whatever the
route (a third-party library pulling one in, an ``importlib`` call). The static half, the import
contract over every import statement and the engine's layer order, is
tests/engine/test_import_contract.py.
"""

import subprocess
import sys


def test_engine_import_pulls_in_no_gui_or_vtk():
    code = (
        "import sys, pkgutil, importlib, kneegui\n"
        "for m in pkgutil.walk_packages(kneegui.__path__, 'kneegui.'):\n"
        "    importlib.import_module(m.name)\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
        "('PySide6', 'vtk', 'vtkmodules', 'pyvista', 'pyvistaqt', 'shiboken6', 'matplotlib'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"engine imported: {out.stdout}"
