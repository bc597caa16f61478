"""Binary PLY headers: the elements a file declares, and whether a written file holds them all.

Open3D's PLY writers (`o3d.t.io.write_triangle_mesh`, `write_point_cloud`) print a failed
write (a full disk, a file size limit) and return True, leaving a truncated file: the size
its header declares is what tells a whole file from a cut one.
"""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import numpy as np

from stages.common.errors import BlunfError

TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip

# [name, count, [(property, numpy type, or (count type, item type) for a list)]]
Element = list


def read_header(f: BinaryIO) -> tuple[str | None, list[Element]] | None:
    """(format, elements) of the PLY whose header `f` starts at, `f` left at the first byte
    after it; None when `f` is no PLY or its header is cut. A type the file names that
    TYPES lacks is None."""
    if f.readline().strip() != b"ply":
        return None
    elements: list[Element] = []
    fmt = None
    while True:
        line = f.readline()
        if not line:
            return None
        w = line.decode("ascii", "replace").split()
        if not w or w[0] in ("comment", "obj_info"):
            continue
        if w[0] == "end_header":
            return fmt, elements
        if w[0] == "format":
            fmt = w[1]
        elif w[0] == "element":
            elements.append([w[1], int(w[2]), []])
        elif w[0] == "property" and elements:
            if w[1] == "list":
                elements[-1][2].append((w[4], (TYPES.get(w[2]), TYPES.get(w[3]))))
            else:
                elements[-1][2].append((w[2], TYPES.get(w[1])))


def check_written(path: Path) -> None:
    """A one-line error naming `path` unless the binary PLY there is as long as its header
    says (every list property holding 3 items: a triangle mesh's faces). ASCII files and
    unknown types are not checked."""
    path = Path(path)
    with open(path, "rb") as f:
        got = read_header(f)
        start = f.tell()
    size = path.stat().st_size
    if got is None:
        raise BlunfError(f"{path}: cannot write (its header is cut: {size} bytes; disk full?)")
    fmt, elements = got
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        return
    want = start
    for _, count, props in elements:
        row = 0
        for _, t in props:
            if isinstance(t, tuple):
                if None in t:
                    return
                row += np.dtype(t[0]).itemsize + 3 * np.dtype(t[1]).itemsize
            elif t is None:
                return
            else:
                row += np.dtype(t).itemsize
        want += count * row
    if size < want:
        raise BlunfError(f"{path}: cannot write ({size} of {want} bytes written; disk full?)")
