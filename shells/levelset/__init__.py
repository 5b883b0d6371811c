"""Shell extraction (§3.3): grid sampling, level-set dilation / erosion, marching cubes, I/O.

grid.py (sample f, s) -> evolve.py (SDF+, SDF-) -> mesh.py (M+, M-, PLY) -> extract.py
(the whole step, stats, all-or-nothing output) and figure.py (Fig. 5-like slice).
"""

from shells.levelset.extract import Shells, extract_shells, write_shells
from shells.levelset.figure import slice_figure
from shells.levelset.grid import sample_grid
from shells.levelset.mesh import load_ply, write_ply

__all__ = ["Shells", "extract_shells", "write_shells", "slice_figure", "sample_grid",
           "load_ply", "write_ply"]
