"""shells: Adaptive Shells for efficient neural radiance field rendering (Wang et al. 2023).

Pipeline: posed photos -> stage-1 NeuS training with a spatially varying kernel (`train`) ->
shell extraction by level-set dilation/erosion (`levelset`) -> narrow-band rendering by ray
casting the shells with Mitsuba and evaluating the field in Dr.Jit (`render`).
"""

__version__ = "0.1.0"
