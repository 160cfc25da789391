"""Walk-through: fit a shape, check it, sample it, query it, and draw it (matplotlib, off-screen).

    python walkthrough.py picture.png
"""

from __future__ import annotations

import sys

import matplotlib

matplotlib.use("Agg")  # off-screen
import matplotlib.pyplot as plt
import numpy as np

import ism

out = sys.argv[1] if len(sys.argv) > 1 else "walkthrough.png"

# 1. Fit a curve: the zero set of an expression over a box (as `ism fit --expr`).
model, report = ism.fit("x^4 + y^4 - 0.3", (-1, 1, -1, 1), resolution=6, tolerance=1e-3)
print(model)
print(f"fit: max |g|/|grad g| = {report['maxDistance']:.2e}, tolerance met: {report['toleranceMet']}")

# 2. The model's arrays are numpy views.
print("vertices", model.vertices.shape, model.vertices.dtype, "simplices", model.simplices.shape, model.simplices.dtype)
for s in model.stages:
    print(f"  stage {s.kind} degree {s.degree} {s.direction}: {s.num_faces} faces, {len(s.points)} point coordinates")

# 3. Validate: every stage certified a diffeomorphism.
rep = model.validate()
print("validate:", rep.verdict, rep.certificates)

# 4. Sample the curve uniformly by length, with normals; query F on a grid.
pts = model.sample_surface(400, seed=1)
xs, ys = np.meshgrid(np.linspace(-1, 1, 161), np.linspace(-1, 1, 161))
q = model.query(np.column_stack([xs.ravel(), ys.ravel()]))
F = (q["f"] - model.level).reshape(xs.shape)

# 5. Draw: the complex, F, the curved shape, samples with normals.
fig, ax = plt.subplots(figsize=(6, 6))
ax.contourf(xs, ys, F, levels=20, cmap="RdBu_r", alpha=0.6)
ax.triplot(model.vertices[:, 0], model.vertices[:, 1], model.simplices.astype(np.int64), color="0.6", lw=0.3)
curve = model.extract_surface(1e-4)
for line in curve.polylines():
    ax.plot(curve.positions[line, 0], curve.positions[line, 1], "k-", lw=1.5)
ax.quiver(pts["x"], pts["y"], pts["nx"], pts["ny"], color="tab:red", scale=25, width=0.003)
ax.set_aspect("equal")
ax.set_title(f"x⁴ + y⁴ = 0.3: {model.num_simplices} triangles, {rep.verdict}")
fig.savefig(out, dpi=120, bbox_inches="tight")
print("wrote", out)
