"""Vertices of a PLY file (ASCII or binary, mesh or point cloud) with numpy only."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[tuple[str, str, str | None]] = field(default_factory=list)
    """(name, type, list-count type or None)."""


def _ply_header(path: Path, data: bytes) -> tuple[str, list[_PlyElement], int]:
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
    body = data.index(b"\n", end) + 1
    fmt, elements = "", []
    for lineno, line in enumerate(data[:end].decode("ascii", errors="replace").splitlines(), start=1):
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append(_PlyElement(words[1], int(words[2])))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1].properties.append((words[4], words[3], words[2]))
            else:
                elements[-1].properties.append((words[2], words[1], None))
        else:
            raise ValueError(f"{path}:{lineno}: unexpected PLY header line {line.strip()!r}")
    for el in elements:
        for name, typ, count_type in el.properties:
            if typ not in _PLY_TYPES or (count_type is not None and count_type not in _PLY_TYPES):
                raise ValueError(f"{path}: property {name!r} of element {el.name!r} has unknown type {typ!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{path}: unknown PLY format {fmt!r}")
    return fmt, elements, body


def read_ply_points(path: Path) -> np.ndarray:
    """Vertex positions [N, 3] (float64) of a PLY mesh or point cloud, ASCII or binary; faces are ignored."""
    vertex = read_ply_vertices(path)
    return np.stack([vertex[a] for a in "xyz"], axis=1).reshape(-1, 3)


def read_ply_vertices(path: Path) -> dict[str, np.ndarray]:
    """Every scalar property of the vertices of a PLY file ({name: [N] float64}: x, y, z and whatever else it
    holds, e.g. red, green, blue as 0..255), ASCII or binary; faces are ignored."""
    path = Path(path)
    data = path.read_bytes()
    fmt, elements, offset = _ply_header(path, data)
    vertex = next((el for el in elements if el.name == "vertex"), None)
    if vertex is None:
        raise ValueError(f"{path}: no 'vertex' element in the PLY header")
    names = [p[0] for p in vertex.properties]
    if not {"x", "y", "z"} <= set(names) or any(p[2] is not None for p in vertex.properties):
        raise ValueError(f"{path}: the vertex element needs scalar x, y, z properties, has {names}")
    if fmt == "ascii":
        lines = data[offset:].decode("ascii", errors="replace").splitlines()
        skip = 0
        for el in elements:  # elements before the vertices take one line per item
            if el is vertex:
                break
            skip += el.count
        rows = [line for line in lines[skip:] if line.strip()][: vertex.count]
        if len(rows) < vertex.count:
            raise ValueError(f"{path}: {len(rows)} vertex lines for {vertex.count} vertices (truncated file?)")
        try:
            table = np.array([row.split()[: len(names)] for row in rows], dtype=np.float64).reshape(-1, len(names))
        except ValueError as err:
            raise ValueError(f"{path}: malformed ASCII vertex line ({err})") from err
        return {name: table[:, k] for k, name in enumerate(names)}
    endian = "<" if fmt == "binary_little_endian" else ">"
    for el in elements:
        if el is vertex:
            break
        offset = _skip_binary_element(path, data, offset, el, endian)
    dtype = np.dtype([(n, endian + _PLY_TYPES[t]) for n, t, _ in vertex.properties])
    if offset + dtype.itemsize * vertex.count > len(data):
        raise ValueError(f"{path}: file ends inside the vertex data (truncated download?)")
    table = np.frombuffer(data, dtype=dtype, count=vertex.count, offset=offset)
    return {name: table[name].astype(np.float64) for name in names}


def _skip_binary_element(path: Path, data: bytes, offset: int, el: _PlyElement, endian: str) -> int:
    if all(c is None for _, _, c in el.properties):
        return offset + el.count * sum(np.dtype(_PLY_TYPES[t]).itemsize for _, t, _ in el.properties)
    for _ in range(el.count):  # list properties (faces before vertices: rare): walk item by item
        for _, typ, count_type in el.properties:
            size = np.dtype(_PLY_TYPES[typ]).itemsize
            if count_type is None:
                offset += size
            else:
                n = int(np.frombuffer(data, endian + _PLY_TYPES[count_type], 1, offset)[0])
                offset += np.dtype(_PLY_TYPES[count_type]).itemsize + n * size
    return offset


def write_ply_points(path: Path, points: np.ndarray, binary: bool = True) -> None:
    """Write points [N, 3] as a PLY point cloud (float32 binary little-endian, or ASCII)."""
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    header = (f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\ncomment written by uw3dgs\n"
              f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            f.write(points.astype("<f4").tobytes())
        else:
            f.write("".join(" ".join(repr(float(v)) for v in p) + "\n" for p in points).encode("ascii"))
