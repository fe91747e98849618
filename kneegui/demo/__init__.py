"""The built-in demo leg: a procedurally generated right (or left) lower extremity FE model.

A deterministic, structured hexahedral model of a 50th-percentile male lower extremity (pelvis and
foot excluded) with femur, tibia, fibula and patella (cortical quad shells over trabecular hexes),
flesh, skin, cruciate and collateral ligaments, menisci, patellar tendon and knee capsule, posed at
9 degrees of flexion. See docs/demo-leg.md.

- :func:`generate_demo_leg` builds it in memory (:class:`DemoLeg`: ``model``, ``setup``,
  ``design``).
- :func:`write_demo` writes ``demo_leg.k`` and ``demo_leg.setup.json``.
- Both take the variant options (:class:`Variant`): tetrahedral, mixed or 10-node tet meshes
  (:mod:`kneegui.demo.tetmesh`), a welded joint (:mod:`kneegui.demo.welded`), the initial
  flexion and the length unit.
"""

from kneegui.demo.design import DemoDesign
from kneegui.demo.generator import PARTS, DemoLeg, Variant, generate_demo_leg, write_demo

__all__ = ["PARTS", "DemoDesign", "DemoLeg", "Variant", "generate_demo_leg", "write_demo"]
