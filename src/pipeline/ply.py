"""The one binary PLY writer (little-endian): vertices with any numeric properties, and
optionally triangles; and the check every PLY reader makes first (:func:`check`,
:func:`check_file`): the data must hold exactly the elements the header declares, since
Open3D reads a file cut short as far as it goes and only warns. Readers stay with their
formats (``init.io.read_ply`` checks its exact layout; meshes are read with Open3D)."""
from __future__ import annotations

import io
import struct
from pathlib import Path
from typing import BinaryIO

import numpy as np

from pipeline import atomic
from pipeline.errors import InputError

_TYPES = {np.dtype("float32"): "float", np.dtype("float64"): "double", np.dtype("uint8"): "uchar",
          np.dtype("int32"): "int"}


def encode(vertex: dict[str, np.ndarray], faces: np.ndarray | None = None, comments: tuple[str, ...] = ()) -> bytes:
    """PLY bytes of ``vertex`` (property name -> ``(N,)`` array of float32, float64,
    uint8 or int32; written in this order and dtype) and ``faces`` (``(F, 3)`` vertex
    indices, written as int32 lists)."""
    columns = {name: np.asarray(col) for name, col in vertex.items()}
    n = len(next(iter(columns.values())))
    for name, col in columns.items():
        if col.shape != (n,) or col.dtype not in _TYPES:
            raise ValueError(f"PLY property {name}: need an ({n},) array of {sorted(map(str, _TYPES))}, "
                             f"got {col.shape} {col.dtype}")
    rec = np.empty(n, dtype=[(name, col.dtype.newbyteorder("<")) for name, col in columns.items()])
    for name, col in columns.items():
        rec[name] = col
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments), f"element vertex {n}",
              *(f"property {_TYPES[col.dtype]} {name}" for name, col in columns.items())]
    body = [rec.tobytes()]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
        face_rec = np.empty(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
        face_rec["n"] = 3
        face_rec["idx"] = faces
        body.append(face_rec.tobytes())
    return ("\n".join(header + ["end_header"]) + "\n").encode("ascii") + b"".join(body)


def write(path: str | Path, vertex: dict[str, np.ndarray], faces: np.ndarray | None = None,
          comments: tuple[str, ...] = ()) -> Path:
    """Write :func:`encode`'s bytes atomically (temp file in the same folder, then rename)."""
    atomic.write_bytes(path, encode(vertex, faces, comments))
    return Path(path)


# --- checking what a header declares against the data --------------------------------------

_TYPES_READ = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
               "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
               "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_ORDERS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}


class _Element:
    """A header's ``element``: its properties as the size of a scalar, or for a list
    ``(length dtype, its struct, item size)``."""

    def __init__(self, name: str, count: int):
        self.name, self.count, self.props = name, count, []

    def __str__(self) -> str:
        return f"{self.count} {'vertices' if self.name == 'vertex' else self.name + 's'}"

    @property
    def lists(self) -> list[tuple]:
        return [p for p in self.props if not isinstance(p, int)]


def check_file(path: str | Path, error: type[InputError] = InputError) -> None:
    """:func:`check` of the file at ``path``, reading no more than needed (a binary file
    without list properties only by its size)."""
    path = Path(path)
    with open(path, "rb") as f:
        order, elements = _header(f, path, error)
        size = path.stat().st_size - f.tell()
        body = f.read() if not order or any(e.lists for e in elements) else b""
    _check_data(body, size, order, elements, path, error)


def check(raw: bytes, path: str | Path, error: type[InputError] = InputError) -> None:
    """Raise ``error`` naming ``path`` unless ``raw`` is a PLY file whose data hold exactly
    the elements its header declares: no fewer (a file cut short) and nothing after them."""
    f = io.BytesIO(raw)
    order, elements = _header(f, path, error)
    _check_data(memoryview(raw)[f.tell():], len(raw) - f.tell(), order, elements, path, error)


def _header(f: BinaryIO, path, error) -> tuple[str, list[_Element]]:
    if f.readline().rstrip(b"\r\n") != b"ply":
        raise error(f"{path}: not a PLY file (no 'ply' magic line)")
    order, elements = None, []
    while line := f.readline():
        words = line.decode("ascii", "replace").split()
        try:
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header" and order is not None:
                return order, elements
            if words[0] == "format":
                order = _ORDERS[words[1]]
            elif words[0] == "element" and int(words[2]) >= 0:
                elements.append(_Element(words[1], int(words[2])))
            elif words[0] == "property" and words[1] == "list":
                length = np.dtype(order + _TYPES_READ[words[2]])
                elements[-1].props.append((length, struct.Struct(order + length.char),
                                           np.dtype(_TYPES_READ[words[3]]).itemsize))
            elif words[0] == "property":
                elements[-1].props.append(np.dtype(_TYPES_READ[words[1]]).itemsize)
            else:
                raise ValueError
        except (IndexError, KeyError, ValueError, TypeError):
            raise error(f"{path}: bad PLY header line {line.decode('ascii', 'replace').strip()!r}") from None
    raise error(f"{path}: PLY header has no end_header line")


def _check_data(body: bytes | memoryview, size: int, order: str, elements: list[_Element], path, error) -> None:
    held, extra = (_binary_walk(body, size, elements) if order else _ascii_walk(body, elements))
    for el, n in zip(elements, held):
        if n < el.count:
            raise error(f"{path}: header declares {el}, file holds {n} (truncated or corrupt)")
    if extra:
        raise error(f"{path}: {extra} {'bytes' if order else 'values'} after the "
                    f"{', '.join(map(str, elements)) or 'no elements'} its header declares")


def _binary_walk(body: bytes, size: int, elements: list[_Element]) -> tuple[list[int], int]:
    """Rows held of each element, in order up to the first one short, and the bytes left
    after them all."""
    off, held = 0, []
    for el in elements:
        if el.lists:
            off, n = _binary_list_rows(body, off, el)
        else:
            row = sum(el.props)
            n = min(el.count, (size - off) // row) if row else el.count
            off += n * row
        held.append(n)
        if n < el.count:
            return held, 0
    return held, size - off


def _binary_row_end(body: bytes, off: int, el: _Element) -> tuple[int | None, list[tuple[int, int]]]:
    """The end of the row at ``off`` (``None`` when the data end first or a list length is
    negative) and its list lengths as (offset, value)."""
    lengths = []
    for p in el.props:
        if isinstance(p, int):
            off += p
            continue
        length, unpack, item = p
        if off + length.itemsize > len(body):
            return None, lengths
        n = int(unpack.unpack_from(body, off)[0])
        if n < 0:
            return None, lengths
        lengths.append((off, n))
        off += length.itemsize + n * item
    return (off if off <= len(body) else None), lengths


def _binary_list_rows(body: bytes, off: int, el: _Element) -> tuple[int, int]:
    """(end offset, rows held) of an element with list properties. Fast where every row has
    the first one's list lengths (a triangle mesh): those are then checked at once."""
    end, lengths = _binary_row_end(body, off, el) if el.count else (None, [])
    if end is not None and off + el.count * (end - off) <= len(body) and all(
            (np.ndarray((el.count,), p[0], body, at, (end - off,)) == n).all()
            for (at, n), p in zip(lengths, el.lists)):
        return off + el.count * (end - off), el.count
    for i in range(el.count):
        end, _ = _binary_row_end(body, off, el)
        if end is None:
            return off, i
        off = end
    return off, el.count


def _ascii_walk(body: bytes, elements: list[_Element]) -> tuple[list[int], int]:
    """As :func:`_binary_walk`, in whitespace-separated values."""
    gap = np.frombuffer(body, np.uint8) <= 32
    starts = np.flatnonzero(~gap & np.r_[True, gap[:-1]])
    ends = np.flatnonzero(~gap & np.r_[gap[1:], True]) + 1
    t, held = 0, []
    for el in elements:
        if el.lists:
            t, n = _ascii_list_rows(body, starts, ends, t, el)
        else:
            n = min(el.count, (len(starts) - t) // len(el.props)) if el.props else el.count
            t += n * len(el.props)
        held.append(n)
        if n < el.count:
            return held, 0
    return held, len(starts) - t


def _ascii_list_rows(body: bytes, starts: np.ndarray, ends: np.ndarray, t: int, el: _Element) -> tuple[int, int]:
    """(next value, rows held) of an element with list properties, from value ``t``."""
    for i in range(el.count):
        row_end = t
        for p in el.props:
            if not isinstance(p, int):
                word = bytes(body[starts[row_end]:ends[row_end]]) if row_end < len(starts) else b""
                if not word.isdigit():  # missing, negative or not a number: the row is not whole
                    return t, i
                row_end += int(word)
            row_end += 1
        if row_end > len(starts):
            return t, i
        t = row_end
    return t, el.count
