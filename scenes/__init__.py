"""Toy data sets rendered with Mitsuba 3 in the Blender/NeRF-synthetic format.

``make_scene(name, out, res=64, views=32, test_views=8, spp=64, seed=0)`` writes one of
``SCENES`` (`sphere`, `fuzzy-sphere`, `core-fuzz`, `thin-parts`, `unbounded`, `white-tube`,
`off-centre`), with a transparent background or on an opaque ``backdrop``; see
``scenes/dataset.py`` for the format and ``scenes/cameras.py`` for the camera conventions.
"""

from scenes.dataset import SCENES, make_scene

__all__ = ["SCENES", "make_scene"]
