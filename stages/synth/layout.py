"""The procedural room's exact architectural layout (gt/layout.json), in the layout stage's
plan.json form: rooms as counter-clockwise interior outlines, walls along them (interior face,
room on the left) with their thickness, openings with their end points on the wall's face."""

from __future__ import annotations

from stages.synth.room import Room

# interior face of each wall, walked counter-clockwise (room on the left)
_FACES = ("wall_south", "wall_east", "wall_north", "wall_west")


def room_layout(room: Room) -> dict:
    """rooms, walls, openings of `room` (metres)."""
    lx, ly = room.size
    poly = [[0.0, 0.0], [lx, 0.0], [lx, ly], [0.0, ly]]
    walls = []
    for i, name in enumerate(_FACES):
        a, b = poly[i], poly[(i + 1) % 4]
        length = abs(b[0] - a[0]) + abs(b[1] - a[1])
        walls.append(
            {
                "name": name,
                "start": a,
                "end": b,
                "thickness": room.wall,
                "length": length,
                "room": 0,
            }
        )
    openings = []
    for d in room.doors:
        i = _FACES.index(d.wall)
        if d.wall in ("wall_south", "wall_north"):
            y = 0.0 if d.wall == "wall_south" else ly
            p, q = [d.start, y], [d.end, y]
        else:
            x = lx if d.wall == "wall_east" else 0.0
            p, q = [x, d.start], [x, d.end]
        width = round(d.width, 6)
        openings.append({"kind": "door", "wall": i, "start": p, "end": q, "width": width})
    return {
        "units": "m",
        "rooms": [{"name": "room 1", "polygon": poly, "area": round(lx * ly, 6)}],
        "walls": walls,
        "openings": openings,
    }
