"""The DVC pipeline itself, on a tiny configuration: it runs end to end, a second
`dvc repro` does nothing, and a change reruns only the stages that read it."""
import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]


def _dvc(cwd: Path, *args: str) -> str:
    exe = Path(sys.executable).with_name("dvc")
    res = subprocess.run([str(exe), *args], cwd=cwd, capture_output=True, text=True)
    assert res.returncode == 0, f"dvc {' '.join(args)} failed:\n{res.stdout}\n{res.stderr}"
    return res.stdout + res.stderr


@pytest.fixture(scope="module")
def tiny_repo(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("pipeline")
    for rel in ("dvc.yaml", "src", "data/raw", "data/published", "models", "reports/speed_accuracy.png"):
        src = REPO / rel
        if src.is_dir():
            shutil.copytree(src, root / rel, ignore=shutil.ignore_patterns("__pycache__", "*.onnx"))
        else:
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src, root / rel)
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["synth"].update(scenes=["synth_relief"], width=160, height=120)
    params["data"].update(width=160, height=120)
    params["optimize"].update(iterations=12, checkpoint_every=5, init_voxel_norm=0.02,
                              downscale=[[0.0, 2], [0.5, 1]], start={"gcf": 0, "nor": 0, "d": 4, "dn": 8, "mv": 7000})
    params["optimize"]["densify"].update(start_iter=4, stop_iter=10, every=4)
    # Two ablation variants, so that a change to one shows which cells rerun.
    params["ablation"]["variants"]["no_priors"] = {"init": "mvs", "loss": {"lambda_gcf": 0.0, "lambda_nor": 0.0}}
    params["ablation"]["run"] = ["baseline_2dgs", "no_priors"]
    # Two scenes, one without ground truth, so that a change to one shows what reruns.
    params["scenes"] = {"synth_relief": {"src": "data/synth/synth_relief", "gt": "data/synth/synth_relief/gt"},
                        "scan24": {"src": "data/raw/dtu/scan24", "gt": None}}
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    subprocess.run(["git", "init", "-q"], cwd=root, check=True)
    _dvc(root, "init", "-q")
    # A clone has commits; dvclive (the optimize stage's curves) fails in a repo without any.
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty", "-m", "init"],
                   cwd=root, check=True)
    return root


def test_repro_runs_then_does_nothing_then_reruns_only_what_changed(tiny_repo):
    first = _dvc(tiny_repo, "repro")
    for stage in ("synth@synth_relief", "prepare@synth_relief", "init@synth_relief", "priors@synth_relief",
                  "baseline@synth_relief", "prepare@scan24", "init@scan24", "baseline@scan24", "baseline-report",
                  "optimize@synth_relief", "mesh@synth_relief", "score@synth_relief", "optimize@scan24",
                  "mesh@scan24", "score@scan24", "variant-train@synth_relief-baseline_2dgs",
                  "variant-score@synth_relief-baseline_2dgs", "variant-train@synth_relief-no_priors",
                  "variant-score@synth_relief-no_priors", "limit@synth_relief", "table1", "table2"):
        assert f"Running stage '{stage}'" in first
    table2 = (tiny_repo / "reports/table2.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in table2] == ["row", "3-view limit (GT seen by the input views)",
                                                        "exact depth through the same meshing",
                                                        "MVS + TSDF (classical)", "baseline_2dgs", "no_priors",
                                                        "full method"]
    rows = list(csv.DictReader(table2))
    means = {r["row"]: float(r["mean"]) for r in rows}
    assert all(0 < float(r["synth_relief_covered"]) <= 1 for r in rows), rows
    # Even at this tiny setting the full method (dense init, priors) must beat plain 2DGS.
    assert means["full method"] < means["baseline_2dgs"], means
    # The 3-view limit invents nothing: its accuracy is near zero and no row's is below it.
    accuracy = {r["row"]: float(r["synth_relief_accuracy"]) for r in rows}
    assert accuracy["3-view limit (GT seen by the input views)"] == min(accuracy.values()) < 0.2, accuracy
    cell = json.loads((tiny_repo / "reports/variants/baseline_2dgs/synth_relief.json").read_text())
    assert cell["chamfer"]["overall_mm"] > 0 and cell["variant"]["init"] == "sfm"
    assert cell["train"]["iterations"] == 12 and cell["timing"]["wall_s"] > 0
    metrics = json.loads((tiny_repo / "reports/metrics/synth_relief.json").read_text())
    assert metrics["chamfer"]["overall_mm"] > 0 and metrics["train"]["iterations"] == 12
    real = json.loads((tiny_repo / "reports/metrics/scan24.json").read_text())
    assert 0 < real["heldout"]["iou_mean"] <= 1 and real["heldout"]["views"] == 46
    assert (tiny_repo / "reports/train/scan24/plots/metrics/train/total.tsv").is_file()
    assert not (tiny_repo / "data/checkpoints/scan24.pt").exists()
    assert (tiny_repo / "data/init/synth_relief/points.ply").is_file()
    assert (tiny_repo / "data/scenes/synth_relief/cameras_sphere.npz").is_file()
    relief = json.loads((tiny_repo / "reports/baseline/synth_relief.json").read_text())
    assert relief["backends"]["mvs"]["cloud"]["points"] > 0 and relief["evaluate"]["status"] == "ok"
    assert (tiny_repo / "data/baseline/synth_relief/mvs_tsdf.ply").is_file()
    table = (tiny_repo / "reports/baseline.md").read_text()
    assert "| synth_relief | mvs |" in table and "| scan24 | no GT |" in table

    second = _dvc(tiny_repo, "repro")
    assert "Running stage" not in second

    # One scene's input changes: only that scene's stages (and the combined table) rerun.
    # (A mask: the synthetic scenes render into scan24's cameras and read its images.)
    mask = tiny_repo / "data/raw/dtu/scan24/mask/024.png"
    pixels = cv2.imread(str(mask), cv2.IMREAD_UNCHANGED)
    pixels[:40, :40] = 255 - pixels[:40, :40]  # survives the resize to 160x120
    assert cv2.imwrite(str(mask), pixels)
    third = _dvc(tiny_repo, "repro")
    for stage in ("prepare@scan24", "init@scan24", "baseline@scan24", "baseline-report"):
        assert f"Running stage '{stage}'" in third
    for stage in ("synth@synth_relief", "prepare@synth_relief", "init@synth_relief", "baseline@synth_relief"):
        assert f"Running stage '{stage}'" not in third
    assert json.loads((tiny_repo / "reports/baseline/synth_relief.json").read_text()) == relief

    # An edit to an init backend's code makes the stages that run backends stale (init,
    # baseline), not the ones that only read the init's files: they rerun only if its outputs change.
    backend = tiny_repo / "src/pipeline/init/mast3r.py"
    original = backend.read_text()
    backend.write_text(original + "\n# an edit\n")
    status = _dvc(tiny_repo, "status")
    assert "init@scan24" in status and "baseline@scan24" in status
    for stage in ("priors@scan24", "optimize@scan24", "mesh@scan24", "score@scan24", "renders@scan24",
                  "variant-train@synth_relief-no_priors", "variant-score@synth_relief-no_priors"):
        assert stage not in status, stage
    backend.write_text(original)

    # A meshing setting reruns the meshing and scoring of every cell, never their training.
    params = yaml.safe_load((tiny_repo / "params.yaml").read_text())
    kept = params["mesh"]["min_component_fraction"]
    params["mesh"]["min_component_fraction"] = kept / 2
    (tiny_repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    status = _dvc(tiny_repo, "status")
    for stage in ("variant-score@synth_relief-no_priors", "variant-score@synth_relief-baseline_2dgs",
                  "mesh@synth_relief", "baseline@synth_relief"):  # the MVS+TSDF baseline meshes too
        assert stage in status, stage
    for stage in ("variant-train@synth_relief-no_priors", "variant-train@synth_relief-baseline_2dgs",
                  "optimize@synth_relief"):
        assert stage not in status, stage
    params["mesh"]["min_component_fraction"] = kept

    params["ablation"]["variants"]["no_priors"]["mesh"] = {"depth": "expected"}
    (tiny_repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    status = _dvc(tiny_repo, "status")
    assert "variant-score@synth_relief-no_priors" in status
    for stage in ("variant-train@synth_relief-baseline_2dgs", "optimize@synth_relief"):
        assert stage not in status

    params["loss"]["lambda_gcf"] = 2.0  # L_gcf on: the priors stage now extracts features too
    (tiny_repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    status = _dvc(tiny_repo, "status")
    for stage in ("priors@scan24", "optimize@scan24", "optimize@synth_relief"):
        assert stage in status
    for stage in ("prepare@scan24", "init@scan24", "baseline@scan24", "synth@synth_relief"):
        assert stage not in status

    params["data"]["width"], params["data"]["height"] = 120, 90
    (tiny_repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    status = _dvc(tiny_repo, "status")
    assert "prepare@synth_relief" in status and "prepare@scan24" in status
    assert "synth@synth_relief" not in status


def test_committed_lock_matches_code_and_params():
    """dvc.lock records the code and params each stage last ran with: a change to a stage's
    code or params committed without `dvc repro` shows here. Dependencies that git does not
    track (other stages' data outputs, absent in a fresh clone) are left to those stages."""
    tracked = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True).stdout.split()

    def is_code(path: str) -> bool:
        return any(f == path or f.startswith(path.rstrip("/") + "/") for f in tracked if not f.endswith(".gitignore"))

    status = json.loads(_dvc(REPO, "status", "--json").strip().splitlines()[-1])
    stale = []
    for stage, entries in status.items():
        for entry in entries:
            if isinstance(entry, str):
                if entry != "always changed":
                    stale.append(f"{stage}: {entry}")
                continue
            for path, state in entry.get("changed deps", {}).items():
                if path == "params.yaml" or is_code(path):
                    stale.append(f"{stage}: {path} {state}")
    assert not stale, "dvc.lock is stale (run `dvc repro` and commit dvc.lock):\n" + "\n".join(stale)
