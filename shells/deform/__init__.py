"""Deformations of a cage: analytic animations, a file of cage poses, and FEM simulation."""

MOTION_HELP = ("still, rigid, bend, twist, wind (analytic), drop, hang (FEM), or an .npz file "
               "with positions [frames, cage vertices, 3]")
