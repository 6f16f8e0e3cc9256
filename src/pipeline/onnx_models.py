"""User-supplied ONNX models, checked against a documented contract.

A :class:`ModelContract` lists the tensors a model must take and give: name, rank,
dtype and optionally some dimensions (an int fixes a dimension, a string names one that
must agree wherever it appears, ``None`` leaves it free). :func:`load_onnx` opens the
file with onnxruntime, compares the model's declared inputs and outputs with the
contract and raises :class:`ModelError` naming the file and every mismatch.
:meth:`OnnxModel.run` validates the arrays it is given and the arrays it returns.

Contracts of the models this package uses are in :data:`CONTRACTS` (documented in
``docs/priors.md``); a stage that needs another model adds its contract there.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import InputError

Dim = int | str | None

# onnxruntime type strings -> numpy dtype names.
_ORT_DTYPES = {
    "tensor(float)": "float32",
    "tensor(float16)": "float16",
    "tensor(double)": "float64",
    "tensor(int64)": "int64",
    "tensor(int32)": "int32",
    "tensor(int8)": "int8",
    "tensor(uint8)": "uint8",
    "tensor(bool)": "bool",
}


class ModelError(InputError):
    """A model file that is missing, unreadable or does not follow its contract."""


@dataclass(frozen=True)
class TensorSpec:
    """One input or output tensor of a model.

    ``shape`` (optional, length ``rank``): an int fixes that dimension, a string is a
    symbol that must take the same value wherever it appears in one call, ``None`` is free.
    """

    name: str
    rank: int
    dtype: str = "float32"
    shape: tuple[Dim, ...] | None = None
    doc: str = ""

    def __post_init__(self) -> None:
        if self.shape is not None and len(self.shape) != self.rank:
            raise ValueError(f"TensorSpec {self.name}: shape {self.shape} does not have rank {self.rank}")
        np.dtype(self.dtype)  # reject unknown dtype names early

    def describe(self) -> str:
        dims = "?" * self.rank if self.shape is None else "x".join("?" if d is None else str(d) for d in self.shape)
        return f"{self.name}: {self.dtype} rank {self.rank} ({dims})"


@dataclass(frozen=True)
class ModelContract:
    """Inputs the model must take (exactly these) and outputs it must give (at least these)."""

    name: str
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]
    doc: str = ""


DSINE_CONTRACT = ModelContract(
    name="dsine",
    inputs=(
        TensorSpec("image", 4, "float32", (1, 3, "H", "W"),
                   "RGB in [0,1] normalised with ImageNet mean/std; H, W multiples of 32 (padded)"),
        TensorSpec("intrinsics", 3, "float32", (1, 3, 3), "pixel intrinsics of the padded image"),
    ),
    outputs=(
        TensorSpec("normal", 4, "float32", (1, 3, "H", "W"),
                   "unit surface normals per pixel in DSINE's camera frame (x right, y up, z towards the viewer)"),
    ),
    doc="DSINE surface-normal estimator (Bae & Davison, CVPR 2024)",
)

VISMVSNET_FEATURES_CONTRACT = ModelContract(
    name="vismvsnet_features",
    inputs=(
        TensorSpec("image", 4, "float32", (1, 3, "H", "W"),
                   "RGB in [0,1], each channel standardised by the image's own mean and std; H, W even"),
    ),
    outputs=(
        TensorSpec("features", 4, "float32", (1, 32, None, None), "32-channel feature map at 1/2 resolution"),
    ),
    doc="Vis-MVSNet feature extractor, finest (1/2 resolution) level (Zhang et al., BMVC 2020)",
)

# Contracts by model kind; stages look theirs up here (the init stage adds MASt3R's).
CONTRACTS: dict[str, ModelContract] = {
    DSINE_CONTRACT.name: DSINE_CONTRACT,
    VISMVSNET_FEATURES_CONTRACT.name: VISMVSNET_FEATURES_CONTRACT,
}


def _check_dims(where: str, spec: TensorSpec, shape, bound: dict[str, int], strict_symbols: bool) -> list[str]:
    """Mismatches between a concrete or declared shape and ``spec.shape``; binds symbols."""
    problems = []
    if spec.shape is None:
        return problems
    for axis, (want, got) in enumerate(zip(spec.shape, shape)):
        if not isinstance(got, (int, np.integer)) or got < 0:
            continue  # symbolic or unknown dimension in the model file: nothing to check
        got = int(got)
        if isinstance(want, int) and got != want:
            problems.append(f"{where} '{spec.name}' dimension {axis} is {got}, contract requires {want}")
        elif isinstance(want, str) and strict_symbols:
            if want in bound and bound[want] != got:
                problems.append(
                    f"{where} '{spec.name}' dimension {axis} ({want}) is {got}, but {want} = {bound[want]} elsewhere"
                )
            bound.setdefault(want, got)
    return problems


class OnnxModel:
    """An onnxruntime session that follows a :class:`ModelContract`."""

    def __init__(self, path: Path, contract: ModelContract, session) -> None:
        self.path = path
        self.contract = contract
        self.session = session

    @property
    def providers(self) -> list[str]:
        return list(self.session.get_providers())

    def run(self, **inputs: np.ndarray) -> dict[str, np.ndarray]:
        """Run the model on named arrays; returns the contract's outputs by name.

        Inputs must match the contract exactly (names, rank, dtype, fixed and shared
        dimensions, finite values); outputs are checked the same way.
        """
        c = self.contract
        want = {s.name for s in c.inputs}
        if set(inputs) != want:
            raise ModelError(
                f"{self.path}: {c.name} model takes inputs {sorted(want)}, got {sorted(inputs)}"
            )
        bound: dict[str, int] = {}
        problems = []
        feed = {}
        for spec in c.inputs:
            arr = np.asarray(inputs[spec.name])
            if arr.ndim != spec.rank:
                problems.append(f"input '{spec.name}' has rank {arr.ndim} (shape {arr.shape}), contract requires {spec.rank}")
                continue
            if arr.dtype != np.dtype(spec.dtype):
                problems.append(f"input '{spec.name}' has dtype {arr.dtype}, contract requires {spec.dtype}")
                continue
            problems += _check_dims("input", spec, arr.shape, bound, strict_symbols=True)
            if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
                problems.append(f"input '{spec.name}' has non-finite values")
            feed[spec.name] = np.ascontiguousarray(arr)
        if problems:
            raise ModelError(f"{self.path}: bad input for the {c.name} model: " + "; ".join(problems))
        names = [s.name for s in c.outputs]
        try:
            values = self.session.run(names, feed)
        except Exception as exc:  # onnxruntime raises its own exception types
            raise ModelError(f"{self.path}: the {c.name} model failed to run: {exc}") from exc
        out = {}
        for spec, arr in zip(c.outputs, values):
            arr = np.asarray(arr)
            if arr.ndim != spec.rank or arr.dtype != np.dtype(spec.dtype):
                problems.append(
                    f"output '{spec.name}' is {arr.dtype} of shape {arr.shape}, contract requires {spec.dtype} rank {spec.rank}"
                )
                continue
            problems += _check_dims("output", spec, arr.shape, bound, strict_symbols=True)
            if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
                problems.append(f"output '{spec.name}' has non-finite values")
            out[spec.name] = arr
        if problems:
            raise ModelError(f"{self.path}: the {c.name} model returned bad output: " + "; ".join(problems))
        return out


def select_providers() -> list[str]:
    """CUDA when onnxruntime offers it, with CPU as the fallback."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    return (["CUDAExecutionProvider"] if "CUDAExecutionProvider" in available else []) + ["CPUExecutionProvider"]


def contract_mismatches(contract: ModelContract, model_inputs, model_outputs) -> list[str]:
    """Differences between a model's declared tensors (onnxruntime ``NodeArg`` lists) and
    a contract: missing or unexpected inputs, missing outputs, rank, dtype, fixed dims."""
    problems = []
    for kind, specs, args, exact in (("input", contract.inputs, model_inputs, True),
                                     ("output", contract.outputs, model_outputs, False)):
        declared = {a.name: a for a in args}
        for spec in specs:
            arg = declared.get(spec.name)
            if arg is None:
                problems.append(f"missing {kind} '{spec.name}' (model has {sorted(declared)})")
                continue
            dtype = _ORT_DTYPES.get(arg.type, arg.type)
            if dtype != spec.dtype:
                problems.append(f"{kind} '{spec.name}' has dtype {dtype}, contract requires {spec.dtype}")
            shape = arg.shape
            if shape is not None and len(shape) != spec.rank:
                problems.append(f"{kind} '{spec.name}' has rank {len(shape)} {list(shape)}, contract requires {spec.rank}")
            elif shape is not None:
                problems += _check_dims(kind, spec, shape, {}, strict_symbols=False)
        if exact:
            extra = sorted(set(declared) - {s.name for s in specs})
            if extra:
                problems.append(f"unexpected {kind}(s) {extra} (contract has {[s.name for s in specs]})")
    return problems


def load_onnx(path: str | Path, contract: ModelContract, providers: list[str] | None = None) -> OnnxModel:
    """Open an ONNX model and check it against ``contract``.

    Raises :class:`ModelError` naming the file when it is missing, cannot be parsed by
    onnxruntime, or differs from the contract (every mismatch is listed).
    """
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: {contract.name} model file not found")
    opts = ort.SessionOptions()
    opts.log_severity_level = 3  # onnxruntime's warnings are noise here; errors still raise
    try:
        session = ort.InferenceSession(str(path), sess_options=opts, providers=providers or select_providers())
    except Exception as exc:  # InvalidProtobuf, Fail, ... depending on how the file is broken
        raise ModelError(f"{path}: not a loadable ONNX model ({type(exc).__name__}: {exc})") from exc
    problems = contract_mismatches(contract, session.get_inputs(), session.get_outputs())
    if problems:
        expected = "; ".join(s.describe() for s in contract.inputs) + " -> " + "; ".join(s.describe() for s in contract.outputs)
        raise ModelError(
            f"{path}: does not follow the {contract.name} contract: " + "; ".join(problems) + f". Expected {expected}"
        )
    return OnnxModel(path, contract, session)
