"""synth_thin's mesh vertices more than 2 mm from the truth, `long` against `paper` (the
ladder's runs): per seed the share beyond 2 and 5 mm, and a picture of seed 2 in two world
projections. Run from the checkout: python thin_tail.py PRESETS_WORK_DIR OUT.png"""
import numpy as np, sys
import matplotlib; matplotlib.use("Agg"); import matplotlib.pyplot as plt
from scipy.spatial import cKDTree
from pipeline.evaluation.gt import read_ground_truth, read_mesh
L, OUT = sys.argv[1], sys.argv[2]  # scripts/presets.py --work folder, the picture
gt = read_ground_truth("data/synth/synth_thin/gt")
tree = cKDTree(gt.points_mm)
stats = {}
for p in ("long", "paper"):
    for s in range(3):
        V, F = read_mesh(f"{L}/{p}/synth_thin/seed{s}/mesh/mesh.ply")
        d, _ = tree.query(V)
        stats[(p, s)] = (V, d)
        print(p, s, "vertices %d, > 2 mm %.2f%%, > 5 mm %.2f%%" % (len(V), 100 * (d > 2).mean(), 100 * (d > 5).mean()))
rows = [("long", 2), ("paper", 2)]
fig, axes = plt.subplots(2, 2, figsize=(10, 9))
for r, key in enumerate(rows):
    V, d = stats[key]
    far = d > 2.0
    for k, (a, b, name) in enumerate([(0, 1, "x-y"), (1, 2, "y-z")]):
        ax = axes[r, k]
        ax.scatter(V[~far, a], V[~far, b], s=0.05, c="0.75", rasterized=True)
        sc = ax.scatter(V[far, a], V[far, b], s=1.5, c=np.minimum(d[far], 10), cmap="autumn_r", vmin=2, vmax=10, rasterized=True)
        ax.set_aspect("equal")
        ax.set_title(f"{key[0]} seed {key[1]}, {name}: {far.mean():.1%} > 2 mm", fontsize=9)
fig.colorbar(sc, ax=axes, shrink=0.5, label="distance to the truth, mm (clipped at 10)")
fig.suptitle("synth_thin mesh vertices more than 2 mm from the truth (colour), the rest grey", fontsize=10)
fig.savefig(OUT, dpi=60)
