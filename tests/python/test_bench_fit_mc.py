"""The distance measures of tools/bench_fit_mc.py (the independent "true error" of BENCHMARKS.md's
fit tables), checked against a peer and against shapes whose distance is known:

- `to_mesh_distance` (exact point-triangle distances, candidates certified; large triangles split)
  against trimesh's `closest_point` (rtree candidates, its own closest-point code) on a mesh with a
  few very large triangles, the case that used to send every point to the slow ball query;
- `read_export_obj` against trimesh's OBJ loader on an `ism export` output;
- `projected_distance` and `exported_distance` on a model whose curved shape is its linear
  isocomplex (the sphere example without its stages): there dist(z, S) is the distance to the
  planar patches, which trimesh measures on the `--linear` export. The projected bound must never
  be below it (it is an upper bound) and must be tight.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import trimesh

ROOT = Path(__file__).resolve().parents[2]

# Agreement with trimesh's closest points: both are float64 closest-point formulas on the same
# triangles, so they differ by rounding only (a few ulps of the coordinates, which are O(1)).
PEER_AGREEMENT = 1e-12


def ism_bin() -> str:
    path = os.environ.get("ISM_BIN") or str(ROOT / "target" / "debug" / "ism")
    assert Path(path).exists(), f"ism binary not found at {path}: build it or set ISM_BIN"
    return path


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_fit_mc", ROOT / "tools" / "bench_fit_mc.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.ISM = ism_bin()
    return mod


def peer_distance(verts, faces, points):
    mesh = trimesh.Trimesh(verts, faces, process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh, points)
    return dist


def test_mesh_distance_matches_trimesh_with_large_triangles(bench):
    rng = np.random.default_rng(7)
    # A fine triangulated sheet plus a few huge triangles far across it: an adaptive mesh's shape.
    n = 24
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    verts = np.stack([u.ravel(), v.ravel(), 0.05 * np.sin(6 * u.ravel()) * v.ravel()], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], axis=-1).reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    big = np.array([[5.0, -3.0, 0.4], [-4.0, 6.0, 0.5], [2.0, 2.0, -5.0], [0.5, 0.5, 0.3]])
    verts = np.concatenate([verts, big])
    m = n * n
    faces = np.concatenate([faces, [[m, m + 1, m + 2], [m, m + 1, m + 3]]])
    points = rng.uniform(-1.0, 2.0, size=(2000, 3))
    dist, near = bench.to_mesh_distance(points, verts, faces, closest=True)
    peer = peer_distance(verts, faces, points)
    # Never farther than trimesh's answer; it agrees almost everywhere, and where it does not,
    # trimesh's candidate search missed the nearest triangle (its answer is the exact distance to
    # a farther one): brute force over every triangle decides.
    assert (dist - peer).max() < PEER_AGREEMENT
    assert np.mean(np.abs(dist - peer) < PEER_AGREEMENT) > 0.99
    tri = verts[faces]
    for c in range(0, len(points), 200):
        p = np.repeat(points[c:c + 200], len(tri), axis=0)
        t = np.tile(tri, (min(200, len(points) - c), 1, 1))
        brute = bench.point_triangle(p, t[:, 0], t[:, 1], t[:, 2]).reshape(-1, len(tri)).min(1)
        assert np.abs(dist[c:c + 200] - brute).max() < PEER_AGREEMENT
    # The closest points are at that distance, and on the mesh (trimesh: 0 from it).
    assert np.abs(np.linalg.norm(points - near, axis=1) - dist).max() < PEER_AGREEMENT
    assert peer_distance(verts, faces, near).max() < PEER_AGREEMENT


def test_split_large_keeps_the_point_set(bench):
    rng = np.random.default_rng(3)
    tri = rng.normal(size=(50, 3, 3))
    tri[:3] *= 40.0
    split = bench.split_large(tri)
    assert len(split) > len(tri)
    # Same area (the pieces tile their triangle) and every piece inside one of the triangles.
    def area(t):
        return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()
    assert area(split) == pytest.approx(area(tri), rel=1e-12)
    verts, faces = tri.reshape(-1, 3), np.arange(len(tri) * 3).reshape(-1, 3)
    assert peer_distance(verts, faces, split.reshape(-1, 3)).max() < PEER_AGREEMENT


@pytest.fixture(scope="module")
def linear_sphere(tmp_path_factory):
    """The sphere example without its stages: its shape S is the linear isocomplex, whose export
    (`--linear`) has exactly S's planar patches."""
    d = tmp_path_factory.mktemp("linear")
    with open(ROOT / "spec" / "examples" / "sphere.ism.json") as f:
        model = json.load(f)
    model["stages"] = []
    path = d / "linear-sphere.ism.json"
    path.write_text(json.dumps(model))
    obj = d / "linear.obj"
    subprocess.run([ism_bin(), "export", str(path), str(obj), "--linear", "-q"], check=True)
    mesh = trimesh.load(obj, process=False, force="mesh")
    return path, np.asarray(mesh.vertices), np.asarray(mesh.faces)


def test_read_export_obj_reads_the_exporter(bench, linear_sphere, tmp_path):
    path, _, _ = linear_sphere
    obj = tmp_path / "curved.obj"
    subprocess.run([ism_bin(), "export", str(path), str(obj), "--tolerance", "1e-3", "-q"],
                   check=True)
    verts, faces = bench.read_export_obj(str(obj))
    mesh = trimesh.load(obj, process=False, force="mesh")
    assert np.array_equal(verts, np.asarray(mesh.vertices))
    assert np.array_equal(faces, np.asarray(mesh.faces))


def test_projected_distance_is_a_tight_upper_bound(bench, linear_sphere):
    path, verts, faces = linear_sphere
    rng = np.random.default_rng(11)
    # Points near S, and a start point near each one's closest point of S (off S by up to 1e-3 in
    # a random direction, as the closest point of a fine export is).
    mesh = trimesh.Trimesh(verts, faces, process=False)
    on, _ = trimesh.sample.sample_surface(mesh, 3000, seed=5)
    z = on + rng.normal(scale=0.02, size=on.shape)
    truth = peer_distance(verts, faces, z)
    near, _, _ = trimesh.proximity.closest_point(mesh, z)
    q = near + rng.normal(scale=1e-3 / np.sqrt(3), size=near.shape)
    bound = bench.projected_distance(str(path), z, q, 2.0)
    ok = np.isfinite(bound)
    assert ok.mean() > 0.95
    # Never below the truth (an upper bound), up to rounding of the 40-step bracket.
    assert (bound[ok] - truth[ok]).min() > -1e-9
    # Tight: the projection of q lands within ~|q - near| of the closest point, and the bound
    # exceeds the truth by second order in that offset relative to the distance, plus where the
    # projection crosses onto another patch — far below the 1e-3 offset itself on average.
    assert np.median(bound[ok] - truth[ok]) < 1e-4


def test_exported_distance_is_the_distance_to_the_shape(bench, linear_sphere, tmp_path):
    path, verts, faces = linear_sphere
    rng = np.random.default_rng(13)
    mesh = trimesh.Trimesh(verts, faces, process=False)
    on, _ = trimesh.sample.sample_surface(mesh, 2000, seed=9)
    z = on + rng.normal(scale=0.01, size=on.shape)
    d, near, eps, ntri, limited = bench.exported_distance(str(path), z, 2e-3, str(tmp_path))
    truth = peer_distance(verts, faces, z)
    # The curved export of a stage-free model lies on its planar patches (its vertices up to the
    # inversion's rounding): the same distances, within the export's chordal tolerance anyway.
    assert eps == pytest.approx(2e-3 * bench.EXPORT_FRACTION)
    assert limited == 0 and ntri >= len(faces)
    assert np.abs(d - truth).max() <= eps
    assert np.median(np.abs(d - truth)) < 1e-12
    assert np.abs(np.linalg.norm(z - near, axis=1) - d).max() < PEER_AGREEMENT
