"""The neural field (§4.1): hash grid, SH encoding, geometry + radiance MLPs, NeuS density.

torch (training): `network.ShellField`, `hashgrid.HashGrid`, `encoding.sh_encode`,
`neus.neus_alpha` / `neus.density` / `neus.composite`.
Dr.Jit (inference): `drjit_field.DrJitField` (imports Mitsuba).
Import the modules themselves; this package re-exports nothing.
"""
