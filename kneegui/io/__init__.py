"""Reading and writing model files: LS-DYNA keyword decks, Abaqus .inp and VTK .vtu export."""
