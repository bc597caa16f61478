"""The procedural room's exact architectural layout (gt/layout.json), in the layout stage's
plan.json form: rooms as counter-clockwise interior outlines, walls along them (interior face,
room on the left) with their thickness, openings (kind door or passage; a passage with `top`,
its lintel's underside or the wall's height) with their end points on the wall's face."""

from __future__ import annotations

from stages.synth.room import Room
from stages.synth.shape import faces_of


def room_layout(room: Room) -> dict:
    """rooms, walls, openings of `room` (metres); a rectangle's walls are, counter-clockwise
    from the origin, wall_south, wall_east, wall_north, wall_west."""
    poly = [[float(x), float(y)] for x, y in room.polygon]
    faces = faces_of(room.polygon, room.wall, room.height)
    walls = []
    for f in faces:
        walls.append(
            {
                "name": f.name,
                "start": list(f.a),
                "end": list(f.b),
                "thickness": room.wall,
                "length": f.length,
                "room": 0,
            }
        )
    names = [f.name for f in faces]
    openings = []
    for d in room.doors:
        i = names.index(d.wall)
        f = faces[i]
        if f.along_x:
            p, q = [d.start, f.a[1]], [d.end, f.a[1]]
        else:
            p, q = [f.a[0], d.start], [f.a[0], d.end]
        width = round(d.width, 6)
        o = {"kind": d.kind, "wall": i, "start": p, "end": q, "width": width}
        if d.kind == "passage":  # the lintel's underside (the wall's height: none)
            o["top"] = room.height if d.top is None else d.top
        openings.append(o)
    x, y = [p[0] for p in poly], [p[1] for p in poly]
    area = 0.5 * sum(x[i - 1] * y[i] - x[i] * y[i - 1] for i in range(len(poly)))
    return {
        "units": "m",
        "rooms": [{"name": "room 1", "polygon": poly, "area": round(area, 6)}],
        "walls": walls,
        "openings": openings,
    }
