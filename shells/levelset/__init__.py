"""Shell extraction (§3.3): grid sampling, level-set dilation / erosion, marching cubes, I/O.

grid.py (sample f, s) -> evolve.py (SDF+, SDF-) -> mesh.py (M+, M-, PLY) -> extract.py
(the whole step, stats, all-or-nothing output) and figure.py (Fig. 5-like slice).
Import the modules themselves; this package re-exports nothing.
"""
