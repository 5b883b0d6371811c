"""Shading of packed samples in Dr.Jit: one field evaluation, NeuS alpha, front-to-back
compositing, and what a ray sees behind its last sample. Shared by the band / full renderer
(`shells.render.frame`) and the occupancy-grid baseline (`shells.render.occupancy`).

The torch twins for padded [R, S] samples are `shells.fields.neus.composite` (stage 1 and the
differentiable band renderer `shells.render.band`).
"""

from __future__ import annotations

from typing import Any

import drjit as dr
import mitsuba as mi

from shells.fields.neus import neus_alpha
from shells.render.sampler import PackedSamples

WHITE = (1.0, 1.0, 1.0)  # the default background (config data.background)


@dr.syntax
def composite_packed(alpha: Any,  # mi.Float [M] packed per ray, front to back
                     rgb: Any,  # mi.Color3f [M]
                     start: Any,  # mi.UInt32 [R] first sample of each ray
                     count: Any,  # mi.UInt32 [R] samples per ray
                     background: Any,  # mi.Color3f, width 1 or R
                     ) -> tuple[Any, Any]:  # colour mi.Color3f [R], opacity mi.Float [R]
    """C = sum_i T_i alpha_i c_i + T_n bg, T_i = prod_{j<i} (1 - alpha_j), per ray."""
    i = mi.UInt32(0)  # sample index within the ray
    trans = dr.ones(mi.Float, dr.width(count))  # transmittance T_i
    acc = dr.zeros(mi.Color3f, dr.width(count))  # accumulated colour
    while dr.hint(i < count, max_iterations=-1, label="composite"):
        idx = start + i
        a = dr.gather(mi.Float, alpha, idx)
        acc += (trans * a) * dr.gather(mi.Color3f, rgb, idx)
        trans *= 1.0 - a
        i += 1
    return acc + trans * background, 1.0 - trans


def shade_samples(field: Any, samples: PackedSamples, o: Any, d: Any,
                  normals: bool = False) -> tuple[Any, ...]:
    """One batched field evaluation at the packed samples: alpha [M], rgb [M] (and the
    field's normal [M] as a third output when ``normals``)."""
    ro = dr.gather(mi.Point3f, o, samples.ray)
    rd = dr.gather(mi.Vector3f, d, samples.ray)
    x = dr.fma(rd, samples.t, ro)
    f = field.eval(x, rd)
    alpha = neus_alpha(f.sdf, f.s, dr.dot(rd, f.normal), samples.delta)
    rgb = mi.Color3f(f.rgb)
    # One kernel for all outputs: compositing gathers from them, and a gather source that
    # is still symbolic gets evaluated on its own (the field would run once per output).
    if normals:
        n = mi.Color3f(f.normal)
        dr.eval(alpha, rgb, n)
        return alpha, rgb, n
    dr.eval(alpha, rgb)
    return alpha, rgb


def end_colour(rgb: Any,  # mi.Color3f [M] packed sample colours
               samples: PackedSamples,  # with .solid (shells.render.sampler.solid_end)
               background: Any,  # mi.Color3f, width 1
               ) -> Any:  # mi.Color3f [R]
    """What each ray sees behind its last sample: the last sample's colour on the rays that
    `shells.render.sampler.solid_end` marks solid, the background on the others."""
    if samples.solid is None:
        return background
    last = dr.gather(mi.Color3f, rgb, samples.start + samples.count - 1, samples.solid)
    return dr.select(samples.solid, last, background)
