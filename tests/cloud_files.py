"""Small binary PCD / PLY writers for the reader tests: every field written with the dtype given, independently
of Open3D's writers (so the tests check what Open3D's reader makes of a file that another tool wrote)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: numpy dtype -> (PCD TYPE, PLY property type)
_TYPES = {
    np.dtype("float32"): ("F", "float"), np.dtype("float64"): ("F", "double"),
    np.dtype("uint32"): ("U", "uint"), np.dtype("int32"): ("I", "int"),
    np.dtype("uint16"): ("U", "ushort"), np.dtype("uint8"): ("U", "uchar"),
    np.dtype("uint64"): ("U", None), np.dtype("int64"): ("I", None),
}


def _table(columns: dict[str, np.ndarray]) -> np.ndarray:
    n = len(next(iter(columns.values())))
    table = np.zeros(n, dtype=np.dtype([(name, values.dtype.newbyteorder("<")) for name, values in columns.items()]))
    for name, values in columns.items():
        table[name] = values
    return table


def write_pcd(path: Path, columns: dict[str, np.ndarray]) -> Path:
    """A ``DATA binary`` PCD with one field per column (name -> (N,) array, its dtype kept)."""
    table = _table(columns)
    types = [_TYPES[np.dtype(v.dtype)][0] for v in columns.values()]
    sizes = [np.dtype(v.dtype).itemsize for v in columns.values()]
    n = len(table)
    header = (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {' '.join(columns)}\n"
              f"SIZE {' '.join(map(str, sizes))}\nTYPE {' '.join(types)}\nCOUNT {' '.join('1' for _ in columns)}\n"
              f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n")
    path.write_bytes(header.encode() + table.tobytes())
    return path


def write_ply(path: Path, columns: dict[str, np.ndarray]) -> Path:
    """A ``binary_little_endian`` PLY with one vertex property per column."""
    table = _table(columns)
    props = "".join(f"property {_TYPES[np.dtype(v.dtype)][1]} {name}\n" for name, v in columns.items())
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(table)}\n{props}end_header\n"
    path.write_bytes(header.encode() + table.tobytes())
    return path


def xyz_columns(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    xyz = rng.normal(scale=5.0, size=(n, 3)).astype(np.float32)
    return {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
