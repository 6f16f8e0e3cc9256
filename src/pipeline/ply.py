"""The one binary PLY writer (little-endian): vertices with any numeric properties, and
optionally triangles. Readers stay with their formats (``init.io.read_ply`` checks its
exact layout; meshes are read with Open3D)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import atomic

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
