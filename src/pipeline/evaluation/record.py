"""The per-scene metrics record (``reports/metrics/NAME.json``, ``reports/variants/V/NAME.json``):
one typed definition that the runs write and the reports read, so a figure has one name
and a malformed or missing one is an error naming the file and the field.

Layout (JSON)::

    scene    str
    train    {iterations, surfels_init, surfels_final, removed_degenerate, preset, backend, masks}
    timing   {wall_s, cpu_s, s_per_iteration, peak_rss_mb, split_s}
    mesh     {triangles_kept, components_kept, views_virtual}
    chamfer  Chamfer (scenes with ground truth)        | exactly one of the two
    heldout  HeldOut (scenes without: held-out views)  |
    variant  {name, init, optimize, loss, mesh}       (ablation cells only)
    provenance {commit, date, cpu, load_average_1min, ...}  (speed-accuracy cells only)
    input_depth_error {coverage, median_abs_mm, signed_median_mm, ...}  (synthetic scenes)
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from pipeline import atomic
from pipeline.errors import InputError, MissingInputError

TRAIN_KEYS = ("iterations", "surfels_init", "surfels_final", "removed_degenerate", "preset", "backend", "masks")
TIMING_KEYS = ("wall_s", "cpu_s", "s_per_iteration", "peak_rss_mb", "split_s")
MESH_KEYS = ("triangles_kept", "components_kept", "views_virtual")


class MetricsError(InputError):
    """A metrics file that cannot be read or lacks a figure; the message names the file."""


def _number(data: dict, key: str, where: str, finite: bool = True, optional: bool = False) -> float | None:
    value = data.get(key)
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (finite and not math.isfinite(value)):
        raise MetricsError(f"{where}: `{key}` must be a {'finite ' if finite else ''}number, got {value!r}")
    return float(value)


def _nan(value: float | None) -> float:
    return math.nan if value is None else value


def _json_number(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else value  # JSON has no NaN: null


def _groups(groups: dict | None) -> dict | None:
    """A split of accuracy or completeness (by views seen, by distance band) with JSON's
    nulls (an empty group) back to NaN."""
    if groups is None:
        return None
    return {g: {k: _nan(v) for k, v in r.items()} for g, r in groups.items()}


def distance_band_key(lo_mm: float, hi_mm: float) -> str:
    """The key of the distance band ``[lo_mm, hi_mm)`` in ``*_by_distance`` (``"0.5-1"``)."""
    return f"{lo_mm:g}-{hi_mm:g}"


def distance_band_lower_mm(key: str) -> float:
    """The lower edge (mm) of the band named ``key`` by :func:`distance_band_key`."""
    lo, sep, hi = key.partition("-")
    try:
        if not sep:
            raise ValueError
        float(hi)
        return float(lo)
    except ValueError:
        raise MetricsError(f"distance band {key!r} is not 'lo-hi' in mm") from None


# The splits of accuracy and completeness a Chamfer record keeps (each optional: a real scan has
# no views-seen split, reports scored before a split existed lack it).
SPLITS = ("accuracy_by_views_seen", "completeness_by_views_seen", "accuracy_by_distance", "completeness_by_distance")


@dataclass(frozen=True)
class Chamfer:
    """DTU Chamfer figures of a mesh (world mm; NaN where undefined, then ``valid`` is false)."""

    accuracy_mm: float
    completeness_mm: float
    overall_mm: float
    valid: bool
    problems: tuple[str, ...] = ()
    counts: dict = field(default_factory=dict)
    accuracy_by_views_seen: dict | None = None  # pipeline.evaluation.seen; synthetic scenes
    completeness_by_views_seen: dict | None = None  # likewise
    accuracy_by_distance: dict | None = None  # dtu_eval.by_distance: band -> fraction, share of the mean
    completeness_by_distance: dict | None = None  # likewise

    @classmethod
    def of(cls, metrics: dict) -> Chamfer:
        """From :func:`pipeline.evaluation.dtu_eval.evaluate_mesh`'s result."""
        return cls(metrics["accuracy_mm"], metrics["completeness_mm"], metrics["overall_mm"], bool(metrics["valid"]),
                   tuple(metrics["problems"]), dict(metrics["counts"]),
                   **{key: _groups(metrics.get(key)) for key in SPLITS})

    @classmethod
    def parse(cls, data: object, where: str) -> Chamfer:
        if not isinstance(data, dict):
            raise MetricsError(f"{where}: Chamfer figures must be an object, got {type(data).__name__}")
        valid = data.get("valid", True)
        nums = {k: _number(data, k, where, finite=False, optional=not valid)
                for k in ("accuracy_mm", "completeness_mm", "overall_mm")}
        return cls(**{k: _nan(v) for k, v in nums.items()}, valid=bool(valid), problems=tuple(data.get("problems", ())),
                   counts=dict(data.get("counts", {})), **{key: _groups(data.get(key)) for key in SPLITS})

    def accuracy_beyond(self, lo_mm: float) -> tuple[float, float]:
        """Share of the accuracy mean (mm) and fraction of the used mesh samples in the distance
        bands from ``lo_mm`` up; NaN where the record has no distance split or no such band."""
        far = [b for key, b in (self.accuracy_by_distance or {}).items() if distance_band_lower_mm(key) >= lo_mm]
        if not far:
            return math.nan, math.nan
        return sum(b.get("share_mm", math.nan) for b in far), sum(b.get("fraction", math.nan) for b in far)

    def figures(self, where: str) -> dict[str, float]:
        """``overall``, ``accuracy``, ``completeness`` (mm), all finite, else an error naming ``where``."""
        out = {"overall": self.overall_mm, "accuracy": self.accuracy_mm, "completeness": self.completeness_mm}
        bad = [k for k, v in out.items() if not math.isfinite(v)]
        if bad:
            raise MetricsError(f"{where}: Chamfer {', '.join(bad)} undefined ({'; '.join(self.problems) or 'no reason given'})")
        return out

    def covered_fraction(self, where: str) -> float:
        """Fraction of the GT points (above the plane) within ``max_dist`` of the mesh. The DTU
        protocol leaves the others out of completeness, so a mesh missing a region entirely is
        not charged for it: this says how much of the object a Chamfer figure covers."""
        used, total = _number(self.counts, "completeness_used", where), _number(self.counts, "gt_above_plane", where)
        if total <= 0:
            raise MetricsError(f"{where}: `gt_above_plane` must be positive, got {total}")
        return used / total

    def to_json(self) -> dict:
        out = {"accuracy_mm": _json_number(self.accuracy_mm), "completeness_mm": _json_number(self.completeness_mm),
               "overall_mm": _json_number(self.overall_mm), "valid": self.valid, "problems": list(self.problems),
               "counts": self.counts}
        for key in SPLITS:
            groups = getattr(self, key)
            if groups is not None:
                out[key] = {g: {k: _json_number(v) for k, v in r.items()} for g, r in groups.items()}
        return out


@dataclass(frozen=True)
class HeldOut:
    """Held-out-view scores of a scene without ground truth (:mod:`pipeline.evaluation.heldout`)."""

    views: int
    size: tuple[int, int]
    iou_mean: float
    hull_iou_mean: float
    psnr_masked_db_mean: float | None
    mesh_iou_mean: float | None = None  # the mesh's silhouette (absent from records written before it)
    per_view: dict = field(default_factory=dict)

    @classmethod
    def parse(cls, data: object, where: str) -> HeldOut:
        if not isinstance(data, dict):
            raise MetricsError(f"{where}: held-out scores must be an object, got {type(data).__name__}")
        return cls(int(_number(data, "views", where)), tuple(data.get("size") or ()), _number(data, "iou_mean", where),
                   _number(data, "hull_iou_mean", where), _number(data, "psnr_masked_db_mean", where, optional=True),
                   _number(data, "mesh_iou_mean", where, optional=True), dict(data.get("per_view", {})))

    def to_json(self) -> dict:
        return {**asdict(self), "size": list(self.size)}


@dataclass(frozen=True)
class SceneMetrics:
    """What ``gcgs score`` (and each ablation cell) writes for one scene."""

    scene: str
    train: dict
    timing: dict
    mesh: dict
    chamfer: Chamfer | None = None
    heldout: HeldOut | None = None
    variant: dict | None = None
    provenance: dict | None = None
    input_depth_error: dict | None = None  # pipeline.evaluation.depth_error; synthetic scenes

    def to_json(self) -> dict:
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["chamfer"] = self.chamfer.to_json() if self.chamfer else None
        out["heldout"] = self.heldout.to_json() if self.heldout else None
        if self.input_depth_error is not None:
            out["input_depth_error"] = {k: _json_number(v) for k, v in self.input_depth_error.items()}
        return {k: v for k, v in out.items() if v is not None}

    def write(self, path: str | Path) -> None:
        atomic.write_text(path, json.dumps(self.to_json(), indent=2, sort_keys=True, allow_nan=False) + "\n")

    @classmethod
    def read(cls, path: str | Path, made_by: str = "run `dvc repro`") -> SceneMetrics:
        path = Path(path)
        if not path.is_file():
            raise MissingInputError(f"{path}: no metrics (file not found; {made_by})")
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise MetricsError(f"{path}: metrics are not valid JSON ({exc})") from exc
        if not isinstance(data, dict):
            raise MetricsError(f"{path}: metrics must be a JSON object, got {type(data).__name__}")
        missing = [k for k in ("scene", "train", "timing", "mesh") if k not in data]
        if missing:
            raise MetricsError(f"{path}: missing {', '.join(f'`{k}`' for k in missing)}")
        if ("chamfer" in data) == ("heldout" in data):
            raise MetricsError(f"{path}: exactly one of `chamfer` (scenes with ground truth) and `heldout` expected")
        where = str(path)
        return cls(scene=data["scene"], train=data["train"], timing=data["timing"], mesh=data["mesh"],
                   chamfer=Chamfer.parse(data["chamfer"], f"{where}: chamfer") if "chamfer" in data else None,
                   heldout=HeldOut.parse(data["heldout"], f"{where}: heldout") if "heldout" in data else None,
                   variant=data.get("variant"), provenance=data.get("provenance"),
                   input_depth_error=data.get("input_depth_error"))
