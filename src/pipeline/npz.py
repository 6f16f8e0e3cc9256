"""Reading ``.npz`` files with errors that name the file and the problem."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def read_npz(path: str | Path, keys: tuple[str, ...], error: type[Exception], what: str) -> dict[str, np.ndarray]:
    """All arrays of ``path``; raises ``error`` when the file is missing, unreadable or
    lacks one of ``keys``. ``what`` names the kind of file in the message."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: file not found")
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # zip/format errors vary; name the file
        raise error(f"{path}: cannot read {what} file ({exc})") from exc
    missing = [k for k in keys if k not in data]
    if missing:
        raise error(f"{path}: missing key(s) {missing}")
    return data
