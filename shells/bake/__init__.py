"""Baked shells: the band's appearance on a few nested, semi-transparent layer meshes with their
colour, opacity and view dependence in textures (one shared UV atlas).

    format   the asset (layers, atlas textures) and its files: layers.glb (glTF 2.0) + asset.json
    render   the compositing rule on Mitsuba's ray casts: torch reference and Dr.Jit kernels
    layers   the layer meshes: level sets of the field, decimated by their own error, unwrapped
    fit      the textures fitted to the photos and to band renders of the field
    run      run-level commands: shells-bake, shells-export --web, shells-view --baked
"""
