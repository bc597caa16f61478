"""Furniture against a wall (segment.py's _absorb): a wall takes the unlabelled triangles within
plane_dist of it (the rounded seams where it meets the floor), but not the top of what stands
against it."""

from __future__ import annotations

import numpy as np
import trimesh

from stages.common.classes import OBJECT, WALL
from stages.semantics import SemanticsConfig
from stages.semantics.segment import segment, triangles
from tests.stages.test_semantics import EDGE, X, Y, Z, _quad, subdivided


def test_the_top_of_a_sofa_against_a_wall_is_the_sofa():
    # a sofa's back (0.8 m) stands against the wall at y = Y; its top's triangles within 3 cm
    # of the wall faced up and joined the wall: a strip of wall over the sofa on the plan
    sofa = trimesh.creation.box(bounds=[(1.0, Y - 0.9, 0.0), (3.0, Y, 0.8)])
    parts = [
        (np.asarray(sofa.vertices), np.asarray(sofa.faces)),
        _quad([(0, 0, 0), (X, 0, 0), (X, Y, 0), (0, Y, 0)], (0, 0, 1)),
        _quad([(0, Y, 0), (X, Y, 0), (X, Y, Z), (0, Y, Z)], (0, -1, 0)),
    ]
    verts, tris = subdivided(parts, EDGE / 2)
    c, n, _ = triangles(verts, tris)
    top = (np.abs(c[:, 2] - 0.8) < 1e-6) & (n[:, 2] > 0.9)
    strip = top & (c[:, 1] > Y - 0.03)  # the top's triangles within plane_dist of the wall
    seg = segment(verts, tris, SemanticsConfig())
    assert strip.sum() > 20 and (seg.cls[top] == OBJECT).all()
    # the wall keeps its own triangles
    wall = (np.abs(c[:, 1] - Y) < 1e-6) & (c[:, 2] > 0.85)
    assert (seg.cls[wall] == WALL).all()
