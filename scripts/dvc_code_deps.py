"""Rewrite each dvc.yaml stage's ``src/pipeline`` deps to exactly the code its command
imports (a folder when every module in it is imported), as tests/test_dvc_closure.py
computes it. Run after adding a stage or an import:  python scripts/dvc_code_deps.py"""
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
from code_closure import SRC, import_closure, stage_commands  # noqa: E402


def minimal(files: set[Path]) -> list[str]:
    out, folders = [], set()
    for f in sorted(files):
        folder = f.parent
        if folder != SRC and all(p in files for p in folder.glob("*.py")):
            folders.add(folder)
    for f in sorted(files):
        if not any(d == f.parent or d in f.parents for d in folders):
            out.append(f.relative_to(REPO).as_posix())
    return sorted(out + [d.relative_to(REPO).as_posix() for d in folders])


text = (REPO / "dvc.yaml").read_text()
for name, (modules, _) in stage_commands(REPO / "dvc.yaml").items():
    want = minimal(set().union(*(import_closure(m) for m in modules)))
    # The stage's block: from "  name:" to the next top-level stage.
    m = re.search(rf"(?ms)^  {re.escape(name)}:\n.*?(?=^  [\w-]+:\n|\Z)", text)
    block = m.group(0)
    lines = block.split("\n")
    idx = [i for i, ln in enumerate(lines) if re.match(r"\s+- src/pipeline", ln)]
    indent = re.match(r"(\s+)- ", lines[idx[0]]).group(1) if idx else None
    if not idx:  # insert after the deps: line
        d = next(i for i, ln in enumerate(lines) if ln.strip() == "deps:")
        indent = re.match(r"(\s*)", lines[d]).group(1) + "  "
        idx = [d + 1]
        lines.insert(d + 1, "")
        new = lines[:idx[0]] + [f"{indent}- {w}" for w in want] + lines[idx[0] + 1:]
    else:
        new = lines[:idx[0]] + [f"{indent}- {w}" for w in want] + [ln for i, ln in enumerate(lines[idx[0]:], idx[0]) if i not in idx]
    text = text.replace(block, "\n".join(new))
(REPO / "dvc.yaml").write_text(text)
print("dvc.yaml code deps updated")
