"""Plane fill: depth where stereo reads nothing, from the room's own planes.

A simplified Manhattan-world stereo (Furukawa et al. 2009) with a "none" label that keeps
stereo on clutter (Gallup et al. 2010): plane hypotheses from the readings stereo and SfM
did make (`hypotheses`), per view SLIC superpixels labelled with a plane or `none` by
alpha-expansion on photo-consistency, agreement with stereo, free space and smoothness
(`view`, `label`, `solve`), then per pixel: readings that agree with their region's plane
or lie in a `none` region stay; readings disagreeing with a well-supported plane within
`boundary_px` of a region's edge drop (stereo fattens objects); plane depth fills the rest
of a region whose plane beats `none` by `margin`; the fills pass the multi-view consistency
check against the other views' merged maps (a wrong single-view choice drops). When the
check drops over `max_dropped` of the fills, the planes it drops that much of fill nothing
(`undo` "plane": the views disagree on them, so the part of their fills that passes is no
better) and the rest is checked again; the fill as a whole is undone when what is left still
drops that much.
"""

from __future__ import annotations

# the fill itself is stages/depth/planes/filling.py: this package's face stays light, as every
# config load imports it for PlanesConfig (the fill brings torch and scipy, ~2 s)
from stages.depth.planes.config import PlanesConfig

__all__ = ["PlanesConfig"]
