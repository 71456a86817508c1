"""PCD and PLY headers, checked against the bytes of the file before anything is read or allocated.

Open3D's readers trust the header: a PCD whose ``POINTS`` says 99,999,999 but holds 31,167 points is read as
99,999,999 points (zeros beyond the data, ASCII) or crashes the process (``binary_compressed``); a PLY whose vertex
count is too large is padded with zeros. So every size the header states is checked here first:
:func:`check_cloud_file` parses the header, checks that its fields agree with each other (``FIELDS`` / ``SIZE`` /
``TYPE`` / ``COUNT``, ``WIDTH * HEIGHT = POINTS``, known property types) and that the data after it holds exactly
what the header describes:

- binary PCD: ``POINTS * point size`` bytes (less than one point of trailing bytes tolerated);
- ``binary_compressed`` PCD: the compressed and uncompressed sizes it starts with (the uncompressed size must be
  ``POINTS * point size``, the compressed size must be present and able to expand that far: LZF expands at most
  :data:`LZF_MAX_RATIO` times);
- ASCII PCD / PLY: one line per point, each with one number per value, every number parsed (integer fields in
  the range of their type);
- binary PLY: the element counts times their row sizes (a lower bound when an element has list properties).

A header that does not describe its data raises :class:`SourceError` naming the file and the field. The caller
reads the file only after that, and checks that the reader returned :attr:`CloudHeader.n_points` points.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from driftmap.errors import NotACloudFile, SourceError

logger = logging.getLogger(__name__)

MAX_HEADER_BYTES = 64 * 1024
"""A PCD / PLY header longer than this is not one (the data is searched for its end otherwise)."""
LZF_MAX_RATIO = 104
"""LZF (PCD ``binary_compressed``) expands a back-reference of 3 bytes into at most 264: no compressed block
expands more than about 88 times (+ margin)."""

#: PCD TYPE -> allowed SIZEs
_PCD_SIZES = {"F": (4, 8), "I": (1, 2, 4, 8), "U": (1, 2, 4, 8)}
_PCD_DATA = ("ascii", "binary", "binary_compressed")
#: PLY property type -> numpy type code
PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass(frozen=True)
class CloudHeader:
    """What a PCD / PLY header says, checked against the data (:func:`check_cloud_file`)."""

    file: Path
    kind: str
    """``"pcd"`` or ``"ply"``."""
    encoding: str
    """PCD ``DATA`` (``ascii``, ``binary``, ``binary_compressed``) or PLY ``format``."""
    n_points: int
    fields: tuple[str, ...]
    """Per-point field (PCD) / vertex property (PLY) names."""
    data_offset: int
    dtype: np.dtype | None
    """Layout of one point in the binary data (PCD ``binary``; PLY binary with fixed-size vertex rows)."""
    viewpoint: tuple[str, ...] | None = None
    """A PCD's ``VIEWPOINT`` as written (``tx ty tz qw qx qy qz``) when it is not the identity ``0 0 0 1 0 0 0``
    (or not 7 numbers); ``None`` for the identity, a PCD without one, and PLY files."""


def check_cloud_file(file: Path) -> CloudHeader:
    """Parse the header of a ``.pcd`` / ``.ply`` file and check it against the data (see the module docs);
    :class:`SourceError` naming the file and the field otherwise."""
    try:
        with file.open("rb") as fh:
            head = fh.read(MAX_HEADER_BYTES)
        size = file.stat().st_size
    except OSError as exc:
        raise SourceError(f"{file}: cannot read ({exc.strerror or exc})") from exc
    if file.suffix.lower() == ".pcd":
        return _check_pcd(file, head, size)
    return _check_ply(file, head, size)


def _header_lines(file: Path, head: bytes, is_end: object, what: str) -> tuple[list[tuple[int, list[str]]], int]:
    """``[(line number, words)]`` of a header up to and including the line ``is_end(words)`` accepts, and the byte
    offset after it."""
    lines: list[tuple[int, list[str]]] = []
    pos = 0
    for lineno in range(1, 10_000):
        end = head.find(b"\n", pos)
        if end < 0:
            break
        text = head[pos:end].decode("ascii", "replace")
        pos = end + 1
        words = text.split()
        lines.append((lineno, words))
        if is_end(words):  # type: ignore[operator]
            return lines, pos
    raise NotACloudFile(file, f"no end of the {what} header in its first {min(len(head), MAX_HEADER_BYTES)} bytes "
                              f"(truncated or not a {what} file)")


def _int_value(file: Path, lineno: int, field: str, text: str, *, minimum: int = 0) -> int:
    try:
        value = int(text)
    except ValueError:
        raise SourceError(f"{file}:{lineno}: header field {field}: {text!r} is not an integer") from None
    if value < minimum:
        raise SourceError(f"{file}:{lineno}: header field {field}: {value} is below {minimum}")
    return value


# ---- PCD -------------------------------------------------------------------------------------------------------


def _pcd_fields(file: Path, lines: list[tuple[int, list[str]]]) -> dict[str, tuple[int, list[str]]]:
    found: dict[str, tuple[int, list[str]]] = {}
    for lineno, words in lines:
        if not words or words[0].startswith("#"):
            continue
        key = words[0]  # the PCD spec spells its keys in capitals: "data ascii" is not a DATA line
        if key in found:
            raise SourceError(f"{file}:{lineno}: header field {key} given twice (also line {found[key][0]})")
        found[key] = (lineno, words[1:])
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT", "DATA"):
        if key not in found:
            raise SourceError(f"{file}: PCD header has no {key} line")
    return found


def _pcd_layout(file: Path, found: dict[str, tuple[int, list[str]]],
                size: int) -> tuple[list[str], list[str], list[int], list[int]]:
    """``(names, types, sizes, counts)`` of the PCD fields, checked against each other and the file's ``size``."""
    names = found["FIELDS"][1]
    n = len(names)
    if n == 0:
        raise SourceError(f"{file}:{found['FIELDS'][0]}: header field FIELDS names no field")
    if len(set(names)) != n:
        twice = sorted({x for x in names if names.count(x) > 1})
        raise SourceError(f"{file}:{found['FIELDS'][0]}: header field FIELDS names {', '.join(twice)} twice")
    counts_line = found.get("COUNT", (found["FIELDS"][0], ["1"] * n))
    for key, (lineno, values) in (("SIZE", found["SIZE"]), ("TYPE", found["TYPE"]), ("COUNT", counts_line)):
        if len(values) != n:
            raise SourceError(f"{file}:{lineno}: header field {key} has {len(values)} entries for the {n} FIELDS")
    types = list(found["TYPE"][1])  # exactly as the spec spells them (F, I, U)
    sizes = [_int_value(file, found["SIZE"][0], "SIZE", v, minimum=1) for v in found["SIZE"][1]]
    counts = [_int_value(file, counts_line[0], "COUNT", v, minimum=1) for v in counts_line[1]]
    if sum(counts) > size:  # every value of a point takes a byte (binary) or more (ASCII)
        raise SourceError(f"{file}:{counts_line[0]}: header field COUNT says {sum(counts)} values per point, more than "
                          f"the {size} bytes of the file hold")
    for name, t, field_bytes in zip(names, types, sizes, strict=True):
        if t not in _PCD_SIZES or field_bytes not in _PCD_SIZES[t]:
            raise SourceError(f"{file}:{found['TYPE'][0]}: header fields TYPE / SIZE: field {name!r} has type {t} of "
                              f"size {field_bytes} (known: F 4/8, I and U 1/2/4/8)")
    for axis in ("x", "y", "z"):
        if axis not in names:
            raise SourceError(f"{file}:{found['FIELDS'][0]}: header field FIELDS has no {axis!r} (fields: "
                              f"{' '.join(names)})")
        if counts[names.index(axis)] != 1:
            raise SourceError(f"{file}:{counts_line[0]}: header field COUNT: coordinate {axis!r} has count "
                              f"{counts[names.index(axis)]}, expected 1")
    return names, types, sizes, counts


def _pcd_dtype(names: list[str], types: list[str], sizes: list[int], counts: list[int]) -> np.dtype:
    kind = {"F": "f", "I": "i", "U": "u"}
    formats = [np.dtype(f"<{kind[t]}{s}") if c == 1 else np.dtype((f"<{kind[t]}{s}", (c,)))
               for t, s, c in zip(types, sizes, counts, strict=True)]
    return np.dtype({"names": names, "formats": formats})


def _check_pcd(file: Path, head: bytes, size: int) -> CloudHeader:
    lines, offset = _header_lines(file, head, lambda w: bool(w) and w[0] == "DATA", "PCD")
    found = _pcd_fields(file, lines)
    names, types, sizes, counts = _pcd_layout(file, found, size)
    width = _int_value(file, found["WIDTH"][0], "WIDTH", (found["WIDTH"][1] or ["?"])[0])
    height = _int_value(file, found["HEIGHT"][0], "HEIGHT", (found["HEIGHT"][1] or ["?"])[0])
    n_points = width * height
    if "POINTS" in found:
        lineno, values = found["POINTS"]
        stated = _int_value(file, lineno, "POINTS", (values or ["?"])[0])
        if stated != n_points:
            raise SourceError(f"{file}:{lineno}: header field POINTS is {stated} but WIDTH * HEIGHT = {width} * "
                              f"{height} = {n_points}: the header contradicts itself")
    lineno, values = found["DATA"]
    encoding = (values or ["?"])[0]  # exactly as the spec spells it
    if encoding not in _PCD_DATA:
        raise SourceError(f"{file}:{lineno}: header field DATA is {encoding!r}; expected one of {', '.join(_PCD_DATA)}")
    dtype = _pcd_dtype(names, types, sizes, counts)
    header = CloudHeader(file, "pcd", encoding, n_points, tuple(names), offset, dtype, _viewpoint(found))
    remaining = size - offset
    if encoding == "binary":
        _check_binary_size(file, "POINTS", n_points, dtype.itemsize, remaining)
    elif encoding == "binary_compressed":
        _check_pcd_compressed(file, n_points, dtype.itemsize, offset, remaining)
    else:
        _check_ascii_rows(file, offset, [(n_points, "POINTS", list(zip(types, sizes, counts, strict=True)))])
    return header


_IDENTITY_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


def _viewpoint(found: dict[str, tuple[int, list[str]]]) -> tuple[str, ...] | None:
    """The ``VIEWPOINT`` words when they are not the identity (:attr:`CloudHeader.viewpoint`)."""
    if "VIEWPOINT" not in found:
        return None
    words = tuple(found["VIEWPOINT"][1])
    try:
        values = tuple(float(w) for w in words)
    except ValueError:
        return words or ("(empty)",)
    return None if values == _IDENTITY_VIEWPOINT else words or ("(empty)",)


def _check_binary_size(file: Path, field: str, n: int, row_bytes: int, remaining: int) -> None:
    need = n * row_bytes
    if remaining < need:
        raise SourceError(f"{file}: header field {field} says {n} points of {row_bytes} bytes ({need} bytes) but the "
                          f"file holds {remaining} bytes of data after the header ({remaining // max(row_bytes, 1)} "
                          f"points): truncated file, or a header that does not describe the data")
    if remaining - need >= max(row_bytes, 1):
        raise SourceError(f"{file}: header field {field} says {n} points of {row_bytes} bytes ({need} bytes) but the "
                          f"file holds {remaining} bytes of data after the header ({remaining // row_bytes} points): "
                          f"the header does not describe the data")


def _check_pcd_compressed(file: Path, n_points: int, point_bytes: int, offset: int, remaining: int) -> None:
    if remaining < 8:
        raise SourceError(f"{file}: binary_compressed PCD without its compressed / uncompressed sizes after the header "
                          f"(truncated file)")
    with file.open("rb") as fh:
        fh.seek(offset)
        compressed, uncompressed = struct.unpack("<II", fh.read(8))
    need = n_points * point_bytes
    if uncompressed != need:
        raise SourceError(f"{file}: binary_compressed data says it expands to {uncompressed} bytes, but header field "
                          f"POINTS ({n_points} points of {point_bytes} bytes) needs {need}: the header does not "
                          f"describe the data")
    if compressed > remaining - 8:
        raise SourceError(f"{file}: binary_compressed data says it has {compressed} compressed bytes, the file holds "
                          f"{remaining - 8} after the header: truncated file")
    if need and (compressed == 0 or compressed * LZF_MAX_RATIO < need):
        raise SourceError(f"{file}: binary_compressed data of {compressed} bytes cannot expand to the {need} bytes of "
                          f"header field POINTS ({n_points} points): the header does not describe the data")


# ---- ASCII bodies ---------------------------------------------------------------------------------------------


def _check_ascii_rows(file: Path, offset: int, elements: list[tuple[int, str, list[tuple[str, int, int]] | None]]) -> None:
    """The data lines after ``offset``: per element ``(count, header field, [(type, size, count)] or None for rows
    of any length)``, one line per row, every value a number that fits its type."""
    try:
        with file.open("rb") as fh:
            fh.seek(offset)
            body = fh.read()
    except OSError as exc:
        raise SourceError(f"{file}: cannot read ({exc.strerror or exc})") from exc
    rows = [line for line in body.split(b"\n") if line.strip()]
    total = sum(n for n, _, _ in elements)
    if len(rows) != total:
        n, field, _ = elements[0]
        stated = f"header field {field} says {n}" if len(elements) == 1 else f"the header's elements hold {total} rows"
        raise SourceError(f"{file}: {stated} but the file has {len(rows)} data lines: truncated file, or a header "
                          f"that does not describe the data")
    start = 0
    for n, field, columns in elements:
        if columns is not None and n:
            _check_ascii_values(file, rows[start:start + n], columns, field)
        start += n


def _check_ascii_values(file: Path, rows: list[bytes], columns: list[tuple[str, int, int]], field: str) -> None:
    width = sum(c for _, _, c in columns)
    lengths = np.fromiter((len(r.split()) for r in rows), dtype=np.int64, count=len(rows))
    wrong = np.flatnonzero(lengths != width)
    if wrong.size:
        k = int(wrong[0])
        raise SourceError(f"{file}: data line {k + 1} ({field}) has {lengths[k]} values, the header gives {width} per "
                          f"point")
    tokens = b" ".join(rows).split()
    try:
        values = np.array(tokens).astype(np.float64).reshape(len(rows), width)
    except ValueError:
        for k, row in enumerate(rows):
            try:
                np.array(row.split()).astype(np.float64)
            except ValueError:
                raise SourceError(f"{file}: data line {k + 1} ({field}) holds a value that is not a number: "
                                  f"{row.decode('ascii', 'replace')[:80]!r}") from None
        raise  # pragma: no cover - some row must have failed
    column = 0
    for kind, size, count in columns:
        block = values[:, column:column + count]
        column += count
        if kind in "IU":
            lo, hi = (0, 2 ** (8 * size) - 1) if kind == "U" else (-(2 ** (8 * size - 1)), 2 ** (8 * size - 1) - 1)
            bad = ~(np.isfinite(block) & (block == np.round(block)) & (block >= lo) & (block <= hi))
            if bad.any():
                k = int(np.flatnonzero(bad.any(axis=1))[0])
                raise SourceError(f"{file}: data line {k + 1} ({field}) holds a value that is not an integer of its "
                                  f"field's type ({kind}{size}, {lo}..{hi})")


# ---- PLY -------------------------------------------------------------------------------------------------------


@dataclass
class _PlyElement:
    name: str
    count: int
    lineno: int
    properties: list[tuple[str, str, str | None]]
    """``(name, numpy code, list count code or None)``."""

    def fixed_dtype(self, endian: str) -> np.dtype | None:
        if any(c is not None for _, _, c in self.properties):
            return None
        return np.dtype([(n, endian + code) for n, code, _ in self.properties]) if self.properties else None

    def min_row_bytes(self) -> int:
        return sum(np.dtype(c if c is not None else code).itemsize for _, code, c in self.properties)


def _ply_elements(file: Path, lines: list[tuple[int, list[str]]]) -> tuple[str, list[_PlyElement]]:
    if not lines or lines[0][1] != ["ply"]:
        raise NotACloudFile(file, "not a PLY file (the first line is not 'ply')")
    encoding: str | None = None
    elements: list[_PlyElement] = []
    for lineno, words in lines[1:-1]:
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            if len(words) < 2 or words[1] not in _PLY_FORMATS:
                raise SourceError(f"{file}:{lineno}: header field format: {' '.join(words[1:])!r}; expected one of "
                                  f"{', '.join(_PLY_FORMATS)}")
            encoding = words[1]
        elif words[0] == "element":
            if len(words) != 3:
                raise SourceError(f"{file}:{lineno}: header field element: expected 'element NAME COUNT'")
            elements.append(_PlyElement(words[1], _int_value(file, lineno, f"element {words[1]}", words[2]), lineno, []))
        elif words[0] == "property":
            _ply_property(file, lineno, words, elements)
        else:
            raise SourceError(f"{file}:{lineno}: unknown PLY header line {' '.join(words)[:60]!r}")
    if encoding is None:
        raise SourceError(f"{file}: PLY header has no format line")
    return encoding, elements


def _ply_property(file: Path, lineno: int, words: list[str], elements: list[_PlyElement]) -> None:
    """Add a ``property`` line to the last element (checked: known types, one name)."""
    if not elements:
        raise SourceError(f"{file}:{lineno}: header field property before any element")
    if words[1:2] == ["list"]:
        if len(words) != 5 or words[2] not in PLY_TYPES or words[3] not in PLY_TYPES or PLY_TYPES[words[2]][0] == "f":
            raise SourceError(f"{file}:{lineno}: header field property list: expected 'property list <integer type> "
                              f"<type> NAME' with known types, got {' '.join(words)!r}")
        elements[-1].properties.append((words[4], PLY_TYPES[words[3]], PLY_TYPES[words[2]]))
        return
    if len(words) != 3 or words[1] not in PLY_TYPES:
        raise SourceError(f"{file}:{lineno}: header field property: expected 'property TYPE NAME' with TYPE one of "
                          f"{', '.join(sorted(PLY_TYPES))}, got {' '.join(words)!r}")
    if any(words[2] == name for name, _, _ in elements[-1].properties):
        raise SourceError(f"{file}:{lineno}: property {words[2]!r} of element {elements[-1].name!r} given twice")
    elements[-1].properties.append((words[2], PLY_TYPES[words[1]], None))


def _check_ply(file: Path, head: bytes, size: int) -> CloudHeader:
    lines, offset = _header_lines(file, head, lambda w: w == ["end_header"], "PLY")
    encoding, elements = _ply_elements(file, lines)
    vertex = next((e for e in elements if e.name == "vertex"), None)
    if vertex is None:
        raise SourceError(f"{file}: PLY header has no vertex element")
    names = [n for n, _, _ in vertex.properties]
    for axis in ("x", "y", "z"):
        if axis not in names:
            raise SourceError(f"{file}:{vertex.lineno}: PLY vertex element has no property {axis!r}")
    endian = _PLY_FORMATS[encoding]
    remaining = size - offset
    if endian is None:
        _check_ascii_rows(file, offset, [(e.count, f"element {e.name}", _ply_columns(e)) for e in elements])
        dtype = None
    elif all(e.fixed_dtype(endian) is not None or e.count == 0 for e in elements):
        row_bytes = {e.name: e.min_row_bytes() for e in elements}
        need = sum(e.count * row_bytes[e.name] for e in elements)
        if len(elements) == 1:
            _check_binary_size(file, f"element vertex {vertex.count}", vertex.count, row_bytes["vertex"], remaining)
        elif remaining < need or remaining - need >= max(min(row_bytes.values()), 1):
            raise SourceError(f"{file}: the header's elements ({', '.join(f'{e.name} {e.count}' for e in elements)}) "
                              f"need {need} bytes but the file holds {remaining} after the header: truncated file, "
                              f"or a header that does not describe the data")
        dtype = vertex.fixed_dtype(endian)
    else:
        need = sum(e.count * e.min_row_bytes() for e in elements)
        if remaining < need:
            raise SourceError(f"{file}: the header's elements ({', '.join(f'{e.name} {e.count}' for e in elements)}) "
                              f"need at least {need} bytes but the file holds {remaining} after the header: "
                              f"truncated file, or a header that does not describe the data")
        dtype = vertex.fixed_dtype(endian)
    before = _bytes_before(elements, vertex)
    return CloudHeader(file, "ply", encoding, vertex.count, tuple(names), offset + (before or 0),
                       dtype if before is not None else None)


def _bytes_before(elements: list[_PlyElement], vertex: _PlyElement) -> int | None:
    """Binary bytes of the elements before the vertex element; ``None`` when one has list properties (then the vertex
    data cannot be located without reading them, and the header's ``dtype`` is left unset)."""
    total = 0
    for e in elements[: elements.index(vertex)]:
        if any(c is not None for _, _, c in e.properties):
            return None
        total += e.count * e.min_row_bytes()
    return total


def _ply_columns(element: _PlyElement) -> list[tuple[str, int, int]] | None:
    """The ASCII value check of an element's rows (``None``: list properties, rows of any length)."""
    if any(c is not None for _, _, c in element.properties):
        return None
    return [(("F" if code[0] == "f" else code[0].upper()), int(code[1]), 1) for _, code, _ in element.properties]
