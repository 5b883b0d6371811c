"""The neural field (§4.1): hash grid, SH encoding, geometry + radiance MLPs, NeuS density.

torch (training): `ShellField` (network.py), `HashGrid` (hashgrid.py), `sh_encode`
(encoding.py), `neus_alpha` / `density` / `composite` (neus.py).
Dr.Jit (inference): `DrJitField` in ``shells.fields.drjit_field`` (imports Mitsuba; not
re-exported here so that training does not pull it in).
"""

from shells.fields.encoding import sh_encode
from shells.fields.hashgrid import HashGrid, hashgrid_reference, level_layout, per_level_scale
from shells.fields.network import ShellField
from shells.fields.neus import composite, density, neus_alpha, phi

__all__ = ["HashGrid", "ShellField", "composite", "density", "hashgrid_reference",
           "level_layout", "neus_alpha", "per_level_scale", "phi", "sh_encode"]
