//! The signed distance to a triangle mesh, [`MeshDistance`]: an R-tree of the triangles with exact
//! closest points in the leaves, the side from the angle-weighted pseudonormals or the winding
//! number ([`super::winding`]), per-thread caches of recent queries, and the enclosures the
//! fitter's certified tests use.

use std::collections::HashMap;
use std::path::PathBuf;

use rstar::{PointDistance, RTree, RTreeObject, SelectionFunction, AABB};

use super::winding::{solid_angle, WindingNode};
use super::{axpy, cross, dot, norm, sub, MeshCheck, TriangleMesh, P3};
use crate::expr::{Enclosure, ImplicitFunction, PvWitness};
use crate::interval::Interval;
use crate::FitError;

#[derive(Clone, Debug)]
pub(super) struct Tri {
    pub(super) id: u32,
    pub(super) v: [P3; 3],
    /// The bounding box of `v`, kept: `rstar` asks for a leaf's envelope before each of its
    /// exact distances (`distance_2_if_less_or_equal`), and rebuilding it there was ~10 % of a
    /// bunny fit (issue 17, session 20).
    env: AABB<P3>,
}

impl Tri {
    pub(super) fn new(id: u32, v: [P3; 3]) -> Tri {
        let lo = [0, 1, 2].map(|k| v[0][k].min(v[1][k]).min(v[2][k]));
        let hi = [0, 1, 2].map(|k| v[0][k].max(v[1][k]).max(v[2][k]));
        Tri {
            id,
            v,
            env: AABB::from_corners(lo, hi),
        }
    }
}

impl RTreeObject for Tri {
    type Envelope = AABB<P3>;
    fn envelope(&self) -> Self::Envelope {
        self.env
    }
}

impl PointDistance for Tri {
    fn distance_2(&self, point: &P3) -> f64 {
        let q = closest_point_on_triangle(*point, self.v);
        let d = sub(*point, q);
        dot(d, d)
    }

    /// rstar's default (the box's distance first, then the exact one), with the inlined
    /// [`box_distance_2`].
    fn distance_2_if_less_or_equal(&self, point: &P3, max_distance_2: f64) -> Option<f64> {
        if box_distance_2(&self.env, point) <= max_distance_2 {
            let d = self.distance_2(point);
            if d <= max_distance_2 {
                return Some(d);
            }
        }
        None
    }
}

/// The closest point of triangle `[a, b, c]` to `p`, by the Voronoi regions of its vertices,
/// edges and face (Ericson, *Real-Time Collision Detection* §5.1.5). Hand-written: it is twenty
/// lines, and the geometry crates that have it (`parry3d`) would pull in a second linear-algebra
/// stack for one function. Needs a triangle of nonzero area.
fn closest_point_on_triangle(p: P3, v: [P3; 3]) -> P3 {
    closest_feature(p, v).0
}

/// Where on a triangle its closest point to a query lies (the Voronoi region Ericson's test ends
/// in): a corner `k`, the edge from corner `k` to corner `k + 1 (mod 3)`, or the face.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Feature {
    Corner(usize),
    Edge(usize),
    Face,
}

/// [`closest_point_on_triangle`] and the [`Feature`] it lies on (the same arithmetic).
fn closest_feature(p: P3, [a, b, c]: [P3; 3]) -> (P3, Feature) {
    let ab = sub(b, a);
    let ac = sub(c, a);
    let ap = sub(p, a);
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return (a, Feature::Corner(0));
    }
    let bp = sub(p, b);
    let d3 = dot(ab, bp);
    let d4 = dot(ac, bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (b, Feature::Corner(1));
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return (axpy(a, d1 / (d1 - d3), ab), Feature::Edge(0));
    }
    let cp = sub(p, c);
    let d5 = dot(ab, cp);
    let d6 = dot(ac, cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (c, Feature::Corner(2));
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return (axpy(a, d2 / (d2 - d6), ac), Feature::Edge(2));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return (
            axpy(b, (d4 - d3) / ((d4 - d3) + (d5 - d6)), sub(c, b)),
            Feature::Edge(1),
        );
    }
    let denom = 1.0 / (va + vb + vc);
    (axpy(axpy(a, vb * denom, ab), vc * denom, ac), Feature::Face)
}

/// Angle-weighted pseudonormals of a closed, consistently oriented manifold mesh with no
/// degenerate triangle (Bærentzen and Aanæs 2005): at a corner the sum of the incident faces'
/// unit normals weighted by their angles there, on an edge the sum of its two faces' normals. For
/// `p` off the surface with closest point `q`, `⟨p − q, n(q)⟩ > 0` exactly when `p` is outside
/// (their Theorem 1), `n(q)` being the face normal, the edge's or the corner's pseudonormal.
#[derive(Debug)]
struct Pseudonormals {
    /// Per vertex.
    corner: Vec<P3>,
    /// Per triangle, its edge `k → k + 1 (mod 3)`.
    edge: Vec<[P3; 3]>,
}

impl Pseudonormals {
    /// `None` unless the mesh is a closed, consistently oriented manifold without degenerate
    /// triangles (the theorem's setting).
    fn new(mesh: &TriangleMesh, check: &MeshCheck, normals: &[P3]) -> Option<Pseudonormals> {
        if !check.is_closed_manifold() || normals.contains(&[0.0; 3]) {
            return None;
        }
        let mut corner = vec![[0.0; 3]; mesh.positions.len()];
        let mut by_edge: HashMap<(u32, u32), P3> = HashMap::with_capacity(3 * normals.len());
        for (t, n) in mesh.triangles.iter().zip(normals) {
            let v = t.map(|i| mesh.positions[i as usize]);
            for k in 0..3 {
                let (e1, e2) = (sub(v[(k + 1) % 3], v[k]), sub(v[(k + 2) % 3], v[k]));
                let angle = norm(cross(e1, e2)).atan2(dot(e1, e2));
                corner[t[k] as usize] = axpy(corner[t[k] as usize], angle, *n);
                let (a, b) = (t[k], t[(k + 1) % 3]);
                let e = by_edge.entry((a.min(b), a.max(b))).or_insert([0.0; 3]);
                *e = axpy(*e, 1.0, *n);
            }
        }
        let edge = mesh
            .triangles
            .iter()
            .map(|t| {
                [0, 1, 2].map(|k| {
                    let (a, b) = (t[k], t[(k + 1) % 3]);
                    by_edge[&(a.min(b), a.max(b))]
                })
            })
            .collect();
        Some(Pseudonormals { corner, edge })
    }
}

/// The pseudonormal sign is used only when `p − q` makes an angle with the pseudonormal farther
/// than this cosine from 90°: rounding in the closest point (a few ulps of the coordinates) then
/// cannot move the sign; nearer to 90° (or at the surface) the winding number decides.
const PSEUDONORMAL_MIN_COS: f64 = 1e-3;

/// ... and only when `|⟨p − q, n⟩|` is above this fraction of the coordinates' size times `|n|`:
/// `q` and `p − q` are ~20 operations on coordinates of that size, so their rounding moves the
/// product by ≲ 10⁻¹⁴ of it; 10⁻¹² keeps a factor of 100. Points nearer the surface than that
/// (the fitter's root bisections end there) take the winding number.
const PSEUDONORMAL_MIN_DOT_REL: f64 = 1e-12;

/// Rounding margin of the value bound, relative to the size of the coordinates: the distance is
/// ~30 operations on coordinates of that size (≲ 10⁻¹⁴ relative); 10⁻⁹ covers it many times
/// over, also for the cancellation in thin triangles.
const VALUE_MARGIN_REL: f64 = 1e-9;

/// Absolute widening of the computed unit normals' components (each is a cross product of
/// differences divided by its length: a few ulps); generous, like [`VALUE_MARGIN_REL`].
const NORMAL_MARGIN: f64 = crate::expr::GENERATOR_ERROR;

/// Normal turn (radians, 60°) across an edge beyond which the Plantinga–Vegter phase is skipped.
/// From 90° on the test can never pass near the edge (every cell on it sees both normals, whose
/// dot product is then ≤ 0). Between 60° and 90° it passes only on cells small enough to see
/// little more than the edge's two sides ([`ImplicitFunction::gradient_generators`]: the nearby
/// normals pairwise; a component-wise box of them already failed from ±35° around an axis on).
/// Kept at 60° because that refinement is costly: the Stanford bunny (82°) at 1e-2 with the phase
/// on ran over 12 CPU-minutes without finishing, against 3.5 with it skipped (session 14).
pub const PV_SHARPEST_EDGE: f64 = std::f64::consts::FRAC_PI_3;

/// [`MeshDistance::enclose`] gathers candidate triangles per sub-box of the box split this many
/// times along each axis (4³ sub-boxes): each level halves the over-reach of the candidate set, which
/// decides how small cells must get before the Plantinga–Vegter test can pass; 64 nearest-point
/// queries per enclosure cost less than the refinement they save (measured on an icosphere).
const GRADIENT_SPLIT_LEVELS: u32 = 2;

/// The signed distance to a mesh, with the winding-number sign (see the module doc).
///
/// Continuous only for a closed, consistently oriented manifold mesh ([`MeshCheck::is_closed_manifold`]):
/// across a hole the winding number passes ½ away from the triangles and `g` jumps from `+d` to
/// `−d` there, which no fit can meet (`ism fit --mesh` refuses such meshes).
#[derive(Debug)]
pub struct MeshDistance {
    mesh: TriangleMesh,
    check: MeshCheck,
    flipped: bool,
    /// Unit normal of each triangle (zero for a degenerate one).
    normals: Vec<P3>,
    tree: RTree<Tri>,
    winding: WindingNode,
    /// The fast sign, for a closed manifold mesh (`None` otherwise: the winding number decides).
    pseudonormals: Option<Pseudonormals>,
    /// Size of the coordinates, for the rounding margins.
    scale: f64,
    /// Key of this instance in the per-thread query caches.
    instance: u64,
    /// Cell size of the cache's grid.
    cache_cell: f64,
}

/// What one evaluation learned, reusable exactly by later queries near it.
#[derive(Clone, Copy, Debug)]
struct Known {
    p: P3,
    /// Distance from `p` to the mesh: the open ball of this radius meets no triangle, so the
    /// winding number, and with it the sign, is constant in it.
    dist: f64,
    inside: bool,
    /// The closest triangle: a nearby query's distance to it bounds its search radius.
    triangle: u32,
}

/// Entries per thread before the cache is cleared: ~12 MB per thread. The fitter revisits a
/// point within one face's Levenberg–Marquardt loop (a few thousand samples), so a small cache
/// keeps nearly all of its hits.
const CACHE_CAPACITY: usize = 1 << 17;

/// A cached sign is reused only within this fraction of the cached distance, so rounding in the
/// distance cannot put the query across the surface.
const CACHE_BALL_FRACTION: f64 = 0.5;

/// Cache grid cell relative to the mesh diagonal: the fitter's finite differences move its sample
/// points by ~10⁻⁷ of a cell, so they land in the cell of the unperturbed point.
const CACHE_CELL_REL: f64 = 1e-6;

static NEXT_INSTANCE: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

thread_local! {
    /// Per-thread cache of recent queries (no locking under rayon): grid cell → what was learned.
    static QUERY_CACHE: std::cell::RefCell<HashMap<(u64, [i64; 3]), Known>> =
        std::cell::RefCell::new(HashMap::new());
    /// This thread's previous (instance, closest triangle): consecutive queries are usually near
    /// each other, so it bounds the next search radius tightly.
    static LAST_TRIANGLE: std::cell::Cell<(u64, u32)> = const { std::cell::Cell::new((u64::MAX, 0)) };
    /// This thread's last [`CANDIDATE_MEMO`] candidate sets: (instance, bits of the box's
    /// corners) → [`MeshDistance::candidates`], oldest first.
    static CANDIDATES: std::cell::RefCell<std::collections::VecDeque<CandidateEntry>> =
        const { std::cell::RefCell::new(std::collections::VecDeque::new()) };
}

/// A memoized candidate set: the instance, the box's corners as bits, the sorted triangle ids.
type CandidateEntry = (u64, [u64; 6], std::rc::Rc<[u32]>);

/// Candidate sets each thread keeps: the Plantinga–Vegter test asks for the same sub-boxes of a
/// cell twice — their enclosures, then, when the hull of those fails, their gradient generators
/// (`PV_SPLIT`³ = 64 sub-boxes, plus the cell's box) — and each set costs 64 nearest-point and 64
/// range queries of the R-tree ([`GRADIENT_SPLIT_LEVELS`]).
const CANDIDATE_MEMO: usize = 160;

impl MeshDistance {
    /// Orients the mesh outward ([`TriangleMesh::orient_outward`]) and builds the R-tree and the
    /// winding hierarchy.
    ///
    /// # Errors
    /// [`FitError::Mesh`] (with an empty path) when every triangle is degenerate.
    pub fn new(mut mesh: TriangleMesh) -> Result<MeshDistance, FitError> {
        let flipped = mesh.orient_outward();
        let check = mesh.check();
        let normals: Vec<P3> = mesh
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|v| mesh.positions[v as usize]);
                let n = cross(sub(b, a), sub(c, a));
                let l = norm(n);
                if l > 0.0 {
                    n.map(|x| x / l)
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        let tris: Vec<Tri> = mesh
            .triangles
            .iter()
            .enumerate()
            .filter(|(i, _)| normals[*i] != [0.0; 3])
            .map(|(i, t)| Tri::new(i as u32, t.map(|v| mesh.positions[v as usize])))
            .collect();
        if tris.is_empty() {
            return Err(FitError::Mesh {
                path: PathBuf::new(),
                source: super::MeshError::AllDegenerate,
            });
        }
        let tree = RTree::bulk_load(tris);
        let mesh_diagonal = mesh.diagonal().max(f64::MIN_POSITIVE);
        let winding = WindingNode::build(tree.root(), &mesh, &mut Vec::new());
        let pseudonormals = Pseudonormals::new(&mesh, &check, &normals);
        let scale = mesh
            .positions
            .iter()
            .flat_map(|p| p.iter().map(|x| x.abs()))
            .fold(0.0, f64::max)
            + mesh.diagonal();
        Ok(MeshDistance {
            mesh,
            check,
            flipped,
            normals,
            tree,
            winding,
            pseudonormals,
            scale,
            instance: NEXT_INSTANCE.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            cache_cell: CACHE_CELL_REL * mesh_diagonal,
        })
    }

    /// The (outward-oriented) mesh.
    pub fn mesh(&self) -> &TriangleMesh {
        &self.mesh
    }

    /// Its combinatorial check.
    pub fn check(&self) -> MeshCheck {
        self.check
    }

    /// Why a fit of this mesh is refused, when it is (`ism fit --mesh` exits 2 with it; the
    /// caller prefixes the mesh's name): not a closed manifold. Across a hole the winding number
    /// passes ½ away from the triangles, where the signed distance jumps from +d to −d; the
    /// fitter would refine that jump to the simplex budget without ever meeting the tolerance.
    pub fn refusal(&self) -> Option<String> {
        let c = &self.check;
        (!c.is_closed_manifold()).then(|| {
            format!(
                "is not a closed manifold ({} boundary, {} non-manifold, {} misoriented edges): \
                 the signed distance would jump where the winding number crosses 1/2 off the \
                 surface; close and orient the mesh first",
                c.boundary_edges, c.nonmanifold_edges, c.misoriented_edges
            )
        })
    }

    /// The largest angle (radians) between the normals of two triangles sharing an edge: above
    /// [`PV_SHARPEST_EDGE`], cells on that edge can fail the Plantinga–Vegter test at every size.
    pub fn sharpest_edge(&self) -> f64 {
        let mut by_edge: HashMap<(u32, u32), Vec<u32>> = HashMap::new();
        for (i, t) in self.mesh.triangles.iter().enumerate() {
            for k in 0..3 {
                let (u, v) = (t[k], t[(k + 1) % 3]);
                by_edge
                    .entry((u.min(v), u.max(v)))
                    .or_default()
                    .push(i as u32);
            }
        }
        let mut worst = 0.0f64;
        for tris in by_edge.values() {
            for (a, &i) in tris.iter().enumerate() {
                for &j in &tris[a + 1..] {
                    let (ni, nj) = (self.normals[i as usize], self.normals[j as usize]);
                    if ni != [0.0; 3] && nj != [0.0; 3] {
                        worst = worst.max(dot(ni, nj).clamp(-1.0, 1.0).acos());
                    }
                }
            }
        }
        worst
    }

    /// Whether [`MeshDistance::new`] turned the mesh inside out to make its volume positive.
    pub fn flipped(&self) -> bool {
        self.flipped
    }

    /// The generalized winding number at `p`, hierarchically (exact up to rounding).
    pub fn winding_number(&self, p: P3) -> f64 {
        self.winding.solid_angle_sum(p) / (4.0 * std::f64::consts::PI)
    }

    /// The generalized winding number at `p` as the plain sum over all triangles (reference).
    pub fn winding_number_brute_force(&self, p: P3) -> f64 {
        self.mesh
            .triangles
            .iter()
            .map(|t| solid_angle(p, t.map(|v| self.mesh.positions[v as usize])))
            .sum::<f64>()
            / (4.0 * std::f64::consts::PI)
    }

    /// The closest point of the mesh to `p` and the triangle it lies on.
    pub fn closest_point(&self, p: P3) -> (P3, u32) {
        // The tree is non-empty (checked in `new`).
        let t = self
            .tree
            .nearest_neighbor(p)
            .expect("the R-tree has at least one triangle");
        (closest_point_on_triangle(p, t.v), t.id)
    }

    /// Whether `p` is inside (`w > ½`).
    pub fn is_inside(&self, p: P3) -> bool {
        self.winding_number(p) > 0.5
    }

    /// Whether `p` is inside, given its closest triangle `t`: the pseudonormal sign when the mesh
    /// is a closed manifold and `p` is clearly off the surface and off the pseudonormal's
    /// perpendicular ([`PSEUDONORMAL_MIN_COS`]), else the winding number. Same answer as
    /// [`MeshDistance::is_inside`] (tested against it) for a dot product instead of a
    /// hierarchical sum of solid angles (the winding number was 70 % of a bunny fit's CPU).
    fn side(&self, p: P3, t: u32) -> bool {
        self.pseudonormal_side(p, t)
            .unwrap_or_else(|| self.is_inside(p))
    }

    /// The pseudonormal half of [`MeshDistance::side`]: `None` when it cannot decide.
    fn pseudonormal_side(&self, p: P3, t: u32) -> Option<bool> {
        let pn = self.pseudonormals.as_ref()?;
        let tri = self.mesh.triangles[t as usize];
        let (q, feature) = closest_feature(p, tri.map(|i| self.mesh.positions[i as usize]));
        let n = match feature {
            Feature::Face => self.normals[t as usize],
            Feature::Edge(k) => pn.edge[t as usize][k],
            Feature::Corner(k) => pn.corner[tri[k] as usize],
        };
        let d = sub(p, q);
        let (ld, ln) = (norm(d), norm(n));
        let s = dot(d, n);
        let clear = ln > 0.0
            && s.abs() > PSEUDONORMAL_MIN_COS * ld * ln
            && s.abs() > PSEUDONORMAL_MIN_DOT_REL * self.scale * ln;
        clear.then_some(s < 0.0)
    }

    /// The closest point and triangle: of the triangles nearest to `p`, the one with the
    /// smallest id (so the answer does not depend on `hint` or the tree's order). A branch-and-bound
    /// descent of the R-tree, nearest child first, with the distance to `hint`'s triangle as the
    /// first bound. It replaced a range query of the ball through `hint`'s closest point: when the
    /// hint was far (the previous query of the thread, another cell), that ball held thousands of
    /// triangles, each measured exactly — 70 % of a bunny fit's CPU (issue 17, session 21). `hint`
    /// is a triangle the R-tree returned, so it is not degenerate.
    fn closest_point_near(&self, p: P3, hint: u32) -> (P3, u32) {
        if hint as usize >= self.mesh.triangles.len() {
            return self.closest_point(p);
        }
        let (d2, t) = self.nearest_triangle(p, hint);
        if d2.is_finite() {
            let v = self.mesh.triangles[t as usize].map(|i| self.mesh.positions[i as usize]);
            (closest_point_on_triangle(p, v), t)
        } else {
            self.closest_point(p)
        }
    }

    /// `(distance², id)` of the triangle nearest to `p` (smallest id among equals), by a
    /// depth-first descent that opens the nearest child first and skips a node or triangle whose
    /// box is farther than the best distance so far, widened by [`NEAREST_SLACK_REL`] so rounding
    /// in the box distance cannot skip a triangle that ties.
    fn nearest_triangle(&self, p: P3, hint: u32) -> (f64, u32) {
        use rstar::RTreeNode;
        let v = self.mesh.triangles[hint as usize].map(|i| self.mesh.positions[i as usize]);
        let dh = sub(p, closest_point_on_triangle(p, v));
        let mut best = (dot(dh, dh), hint);
        let floor = (NEAREST_SLACK_REL * self.scale).powi(2);
        let bound = |b: f64| b * (1.0 + NEAREST_SLACK_REL) + floor;
        let mut stack: Vec<(f64, &rstar::ParentNode<Tri>)> = Vec::with_capacity(64);
        let root = self.tree.root();
        stack.push((box_distance_2(&root.envelope(), &p), root));
        let mut order: Vec<(f64, &rstar::ParentNode<Tri>)> = Vec::with_capacity(16);
        while let Some((d, node)) = stack.pop() {
            if d > bound(best.0) {
                continue;
            }
            order.clear();
            for child in node.children() {
                match child {
                    RTreeNode::Leaf(t) => {
                        if box_distance_2(&t.env, &p) > bound(best.0) {
                            continue;
                        }
                        let d = t.distance_2(&p);
                        if d < best.0 || (d == best.0 && t.id < best.1) {
                            best = (d, t.id);
                        }
                    }
                    RTreeNode::Parent(n) => {
                        let d = box_distance_2(&n.envelope(), &p);
                        if d <= bound(best.0) {
                            order.push((d, n));
                        }
                    }
                }
            }
            // Farthest pushed first, so the nearest child is opened next.
            order.sort_unstable_by(|a, b| b.0.total_cmp(&a.0));
            stack.extend(order.iter().copied());
        }
        best
    }

    /// Distance to the closest point, its triangle, and the side: reuses a cached query in the
    /// same grid cell when `p` lies in its surface-free ball (same sign, exactly) and as the
    /// search hint; otherwise the R-tree and the winding number.
    fn locate(&self, p: P3) -> (P3, u32, bool) {
        let key = (
            self.instance,
            p.map(|x| (x / self.cache_cell).floor() as i64),
        );
        let known = QUERY_CACHE.with(|c| c.borrow().get(&key).copied());
        let last = LAST_TRIANGLE.with(|c| c.get());
        let (q, t) = match known {
            Some(k) => self.closest_point_near(p, k.triangle),
            None if last.0 == self.instance => self.closest_point_near(p, last.1),
            None => self.closest_point(p),
        };
        LAST_TRIANGLE.with(|c| c.set((self.instance, t)));
        let inside = match known {
            Some(k) if norm(sub(p, k.p)) < CACHE_BALL_FRACTION * k.dist => k.inside,
            // On the surface the side is not asked: the value is 0 and the gradient the face
            // normal either way (the fitter's measure queries points of the triangles).
            _ if p == q => false,
            _ => self.side(p, t),
        };
        let dist = norm(sub(p, q));
        if dist > 0.0 {
            QUERY_CACHE.with(|c| {
                let mut c = c.borrow_mut();
                if c.len() >= CACHE_CAPACITY {
                    c.clear();
                }
                c.insert(
                    key,
                    Known {
                        p,
                        dist,
                        inside,
                        triangle: t,
                    },
                );
            });
        }
        (q, t, inside)
    }

    /// Signed distance, its gradient, and the closest point.
    fn evaluate(&self, p: P3) -> (f64, P3) {
        let (q, t, inside) = self.locate(p);
        let d = sub(p, q);
        let dist = norm(d);
        let sign = if inside { -1.0 } else { 1.0 };
        let grad = if dist > 0.0 {
            d.map(|x| sign * x / dist)
        } else {
            self.normals[t as usize]
        };
        (sign * dist, grad)
    }

    /// The 1-Lipschitz bound of `g` over the box `[lo, hi]`: `g(centre) ± half-diagonal`,
    /// widened by the rounding margin.
    pub fn value_bounds(&self, lo: &[f64], hi: &[f64]) -> Interval {
        self.value_bounds_and_nearest(lo, hi).0
    }

    /// [`MeshDistance::value_bounds`] and the triangle nearest to the box's centre.
    fn value_bounds_and_nearest(&self, lo: &[f64], hi: &[f64]) -> (Interval, u32) {
        let (centre, half) = centre_and_half_diagonal(lo, hi);
        let (v, t) = self.value_and_nearest(centre);
        let r = half + VALUE_MARGIN_REL * self.scale;
        (Interval::new(v - r, v + r), t)
    }

    /// `g(p)` and the triangle of its closest point.
    fn value_and_nearest(&self, p: P3) -> (f64, u32) {
        let (q, t, inside) = self.locate(p);
        let dist = norm(sub(p, q));
        (if inside { -dist } else { dist }, t)
    }

    /// Unit-vector bounds containing `∇g` at every point of the box where it exists, or `None`
    /// when the normals there do not avoid the origin (see [`ImplicitFunction::enclose`]).
    fn gradient_bounds(&self, lo: &[f64], hi: &[f64]) -> Option<Vec<Interval>> {
        let ids = self.candidates(lo, hi);
        let mut nlo = [f64::INFINITY; 3];
        let mut nhi = [f64::NEG_INFINITY; 3];
        let mut sum = [0.0; 3];
        let mut normals = Vec::with_capacity(ids.len());
        for &t in ids.iter() {
            let n = self.normals[t as usize];
            for k in 0..3 {
                nlo[k] = nlo[k].min(n[k] - NORMAL_MARGIN);
                nhi[k] = nhi[k].max(n[k] + NORMAL_MARGIN);
                sum[k] += n[k];
            }
            normals.push(n);
        }
        if normals.is_empty() {
            return None;
        }
        // A lower bound r on |u| for u in the convex hull of the normals: the larger of the
        // distance from 0 to their bounding box and the least projection on their mean direction.
        let to_box = (0..3)
            .map(|k| nlo[k].max(0.0).max(-nhi[k]).powi(2))
            .sum::<f64>()
            .sqrt();
        let l = norm(sum);
        let along = if l > 0.0 {
            let m = sum.map(|x| x / l);
            normals
                .iter()
                .map(|&n| dot(n, m) - 3.0 * NORMAL_MARGIN)
                .fold(f64::INFINITY, f64::min)
        } else {
            0.0
        };
        let r = to_box.max(along);
        if r <= 0.0 {
            return None;
        }
        // u_k / |u| with u_k ∈ [lo, hi] and |u| ∈ [r, 1].
        Some(
            (0..3)
                .map(|k| {
                    let a = if nlo[k] >= 0.0 { nlo[k] } else { nlo[k] / r };
                    let b = if nhi[k] >= 0.0 { nhi[k] / r } else { nhi[k] };
                    Interval::new(a.max(-1.0), b.min(1.0))
                })
                .collect(),
        )
    }

    /// The triangles that can hold the closest point of some point of the box `[lo, hi]`,
    /// sorted, without repeats. Gathered per sub-box: a sub-box of half-diagonal h around c needs
    /// the triangles within dist(c) + 2h of c, so splitting shrinks the 2h part, which dominates
    /// near the surface.
    fn candidates(&self, lo: &[f64], hi: &[f64]) -> std::rc::Rc<[u32]> {
        let mut key = [0u64; 6];
        for k in 0..3 {
            key[k] = lo[k].to_bits();
            key[3 + k] = hi[k].to_bits();
        }
        let known = CANDIDATES.with(|m| {
            m.borrow()
                .iter()
                .find(|(i, b, _)| *i == self.instance && *b == key)
                .map(|(_, _, ids)| ids.clone())
        });
        if let Some(ids) = known {
            return ids;
        }
        let ids: std::rc::Rc<[u32]> = self.candidates_uncached(lo, hi).into();
        CANDIDATES.with(|m| {
            let mut m = m.borrow_mut();
            if m.len() >= CANDIDATE_MEMO {
                m.pop_front();
            }
            m.push_back((self.instance, key, ids.clone()));
        });
        ids
    }

    /// A superset of the union of [`MeshDistance::candidates`] over the boxes, sorted, without
    /// repeats: for each box, with centre `C` and half-diagonal `H`, the triangles within
    /// `|g(C)| + 2H` of `C` (and a margin). A triangle a candidate sub-box (centre `c`,
    /// half-diagonal `h`, `|c − C| ≤ H − h`) gathers is within `g(c) + 2h ≤ g(C) + (H − h) + 2h`
    /// of `c`, so within `g(C) + 2H` of `C`. One nearest-point query per box and one traversal,
    /// where the union costs 64 queries and a traversal per box.
    pub(crate) fn candidates_superset(&self, boxes: &[(&[f64], &[f64])]) -> Vec<u32> {
        let mut balls: Vec<(P3, f64)> = Vec::with_capacity(boxes.len());
        for (lo, hi) in boxes {
            let (c, half) = centre_and_half_diagonal(lo, hi);
            let (v, _) = self.value_and_nearest(c);
            // Twice the sub-boxes' margin: their radii and this one's are each rounded.
            let r = v.abs() + 2.0 * half + 4.0 * VALUE_MARGIN_REL * self.scale;
            balls.push((c, r));
        }
        let Some(first) = balls.first() else {
            return Vec::new();
        };
        let centre = first.0;
        self.within_any(balls, centre)
    }

    /// The triangles within any of `balls` (`(centre, radius)`), sorted, each once: one traversal
    /// of the tree ([`WithinAny`]), cut off beyond the ball around `centre` that holds them all.
    fn within_any(&self, balls: Vec<(P3, f64)>, centre: P3) -> Vec<u32> {
        let reach = balls
            .iter()
            .map(|(c, r)| norm(sub(*c, centre)) + r)
            .fold(0.0, f64::max);
        let bound = reach * (1.0 + WITHIN_ANY_MARGIN) + f64::MIN_POSITIVE;
        let select = WithinAny {
            balls: balls.into_iter().map(|(c, r)| (c, r * r)).collect(),
            centre,
            bound2: bound * bound,
        };
        let mut ids: Vec<u32> = self
            .tree
            .locate_with_selection_function(select)
            .map(|t| t.id)
            .collect();
        ids.sort_unstable();
        ids
    }

    /// [`MeshDistance::candidates`] without the memo. Each sub-box's nearest-point query is
    /// bounded by the previous sub-box's closest triangle ([`MeshDistance::closest_point_near`]:
    /// the same distance as the R-tree's nearest neighbour, from a range query instead of its
    /// best-first search), and the sub-boxes' balls are gathered in one traversal of the tree
    /// ([`WithinAny`]: the union of their range queries, each triangle once).
    fn candidates_uncached(&self, lo: &[f64], hi: &[f64]) -> Vec<u32> {
        let mut hint: Option<u32> = None;
        let parts = 1usize << GRADIENT_SPLIT_LEVELS;
        let edge = |k: usize, j: usize| {
            if j == parts {
                hi[k]
            } else {
                lo[k] + (hi[k] - lo[k]) * (j as f64 / parts as f64)
            }
        };
        let mut balls: Vec<(P3, f64)> = Vec::with_capacity(parts * parts * parts);
        for i in 0..parts * parts * parts {
            let j = [i % parts, (i / parts) % parts, i / (parts * parts)];
            let sub_lo = [0, 1, 2].map(|k| edge(k, j[k]));
            let sub_hi = [0, 1, 2].map(|k| edge(k, j[k] + 1));
            let (c, half) = centre_and_half_diagonal(&sub_lo, &sub_hi);
            let (q, t) = match hint {
                Some(h) => self.closest_point_near(c, h),
                None => self.closest_point(c),
            };
            hint = Some(t);
            let radius = norm(sub(c, q)) + 2.0 * half + 2.0 * VALUE_MARGIN_REL * self.scale;
            balls.push((c, radius));
        }
        let (centre, _) = centre_and_half_diagonal(lo, hi);
        self.within_any(balls, centre)
    }
}

/// Relative widening of the best squared distance in [`MeshDistance::nearest_triangle`]'s skip
/// test (and, times the mesh's scale and squared, an absolute floor for points on the surface):
/// a box's distance and a triangle's are computed differently, so a triangle whose distance ties
/// the best must not be skipped for a rounding of its box's.
const NEAREST_SLACK_REL: f64 = 1e-9;

/// Relative widening of [`WithinAny`]'s enclosing ball, so rounding in the triangle inequality
/// cannot make it reject what one of its balls selects.
const WITHIN_ANY_MARGIN: f64 = 1e-6;

/// The union of `locate_within_distance(c, r²)` over the balls `(c, r²)`, in one traversal: a
/// node is opened, a triangle selected, when it passes the same test as in one of those queries
/// (envelope, then exact distance, both `≤ r²`), so the same triangles come out, each once. The
/// enclosing ball (`centre`, `bound2`, containing every ball) only rejects early what no ball can
/// select.
struct WithinAny {
    balls: Vec<(P3, f64)>,
    centre: P3,
    bound2: f64,
}

impl SelectionFunction<Tri> for WithinAny {
    fn should_unpack_parent(&self, envelope: &AABB<P3>) -> bool {
        box_distance_2(envelope, &self.centre) <= self.bound2
            && self
                .balls
                .iter()
                .any(|(c, r2)| box_distance_2(envelope, c) <= *r2)
    }

    fn should_unpack_leaf(&self, leaf: &Tri) -> bool {
        box_distance_2(&leaf.env, &self.centre) <= self.bound2
            && self
                .balls
                .iter()
                .any(|(c, r2)| leaf.distance_2_if_less_or_equal(c, *r2).is_some())
    }
}

/// `envelope.distance_2(p)`, the same number (the per-axis gap to the box, squared and summed in
/// axis order; 0 inside), inlined for `f64` triples: rstar's generic version was the largest
/// single cost of the R-tree descents (43 % of a bunny fit's samples, issue 17, session 21).
#[inline]
fn box_distance_2(envelope: &AABB<P3>, p: &P3) -> f64 {
    let (lo, hi) = (envelope.lower(), envelope.upper());
    let mut s = 0.0;
    for k in 0..3 {
        let gap = if p[k] < lo[k] {
            lo[k] - p[k]
        } else if p[k] > hi[k] {
            p[k] - hi[k]
        } else {
            0.0
        };
        s += gap * gap;
    }
    s
}

fn centre_and_half_diagonal(lo: &[f64], hi: &[f64]) -> ([f64; 3], f64) {
    let mut c = [0.0; 3];
    let mut h2 = 0.0;
    for k in 0..3 {
        c[k] = 0.5 * (lo[k] + hi[k]);
        // The centre is rounded; half the width plus an ulp of the ends bounds |p − c|.
        let w = 0.5 * (hi[k] - lo[k]) + f64::EPSILON * (lo[k].abs() + hi[k].abs());
        h2 += w * w;
    }
    (c, h2.sqrt() * (1.0 + 4.0 * f64::EPSILON))
}

impl ImplicitFunction for MeshDistance {
    fn dim(&self) -> usize {
        3
    }

    fn value(&self, p: &[f64]) -> f64 {
        self.value_and_nearest([p[0], p[1], p[2]]).0
    }

    fn gradient(&self, p: &[f64], gradient: &mut [f64]) -> f64 {
        let (v, g) = self.evaluate([p[0], p[1], p[2]]);
        gradient[..3].copy_from_slice(&g);
        v
    }

    /// Value: [`MeshDistance::value_bounds`]. Gradient: at a point `p` off the surface with
    /// closest point `q`, `∇g(p)` is a unit vector in the cone of the outward normals of the
    /// triangles containing `q` (`p − q` is a proximal normal of the solid, or of its complement
    /// inside; proximal normals lie in the Clarke normal cone, the convex cone of the limiting
    /// normals, which at a mesh point are its faces' normals). Every such triangle lies within
    /// `|g(centre)| + 2·half-diagonal` of the centre, so the R-tree gathers a superset; the unit
    /// vectors of their cone are enclosed by dividing the normals' bounding box by a lower bound
    /// `r` on the length of their convex combinations. On a closed, consistently oriented mesh
    /// only; otherwise (or when the normals surround the origin, as at a sharp corner) there is no
    /// useful enclosure and the gradient is `[-1, 1]` per component, which fails the
    /// Plantinga–Vegter test: cells at sharp features are then refined until the simplex budget.
    /// Returns `None` (no test at all) for an open or non-manifold mesh, where the sign is not a
    /// solid's and the test would not mean what it says.
    fn is_explicit(&self) -> bool {
        true
    }

    /// The exact distance to the triangles: [`MeshDistance::closest_point_near`]'s branch and
    /// bound from this thread's previous closest triangle (no query cache). The measure asks for
    /// it along each patch's lattice, so the previous point's triangle is usually the nearest or
    /// next to it; rstar's best-first `nearest_neighbor` here was 11 % of a bunny fit's CPU
    /// (issue 17, session 23). The same number: both find the least computed distance.
    fn distance_bound(&self, p: &[f64], _reach: f64) -> f64 {
        let p = [p[0], p[1], p[2]];
        let last = LAST_TRIANGLE.with(|c| c.get());
        let (q, t) = if last.0 == self.instance {
            self.closest_point_near(p, last.1)
        } else {
            self.closest_point(p)
        };
        LAST_TRIANGLE.with(|c| c.set((self.instance, t)));
        norm(sub(p, q))
    }

    /// The mesh's triangles, each as its three corners.
    fn surface_triangles(&self) -> Option<Vec<[[f64; 3]; 3]>> {
        let mesh = self.mesh();
        Some(
            mesh.triangles
                .iter()
                .map(|t| t.map(|i| mesh.positions[i as usize]))
                .collect(),
        )
    }

    fn enclose(&self, lo: &[f64], hi: &[f64]) -> Option<Enclosure> {
        if !self.check.is_closed_manifold() {
            return None;
        }
        let value = self.value_bounds(lo, hi);
        let unit = Interval::new(-1.0, 1.0);
        let gradient = if value.contains(0.0) {
            self.gradient_bounds(lo, hi)
                .unwrap_or_else(|| vec![unit; 3])
        } else {
            // 0 ∉ □g already passes the test.
            vec![unit; 3]
        };
        Some(Enclosure { value, gradient })
    }

    /// [`MeshDistance::value_bounds`] and the normal of the triangle nearest to the box's centre
    /// `p` (the same query). It is a generator of every box `B` containing `p`: of `B`'s
    /// candidate sub-boxes ([`MeshDistance::candidates`]) one, with centre `c` and half-diagonal
    /// `h`, contains `p`, and that triangle is within `|c − p| + g(p) ≤ h + (g(c) + h)` of `c`,
    /// inside the ball the sub-box gathers (the rounding is far inside its margin); so its normal
    /// is also inside `B`'s gradient enclosure, which bounds those candidates' normals (or is
    /// the whole unit box).
    fn pv_witness(&self, lo: &[f64], hi: &[f64]) -> Option<PvWitness> {
        if !self.check.is_closed_manifold() {
            return None;
        }
        let (value, t) = self.value_bounds_and_nearest(lo, hi);
        Some(PvWitness {
            value,
            normal: self.normals[t as usize],
            // `enclose`'s branch.
            unit_gradient: !value.contains(0.0),
        })
    }

    /// The normals of [`MeshDistance::candidates_superset`].
    fn gradient_generators_superset(&self, boxes: &[(&[f64], &[f64])], out: &mut Vec<f64>) -> bool {
        if !self.check.is_closed_manifold() {
            return false;
        }
        for t in self.candidates_superset(boxes) {
            out.extend_from_slice(&self.normals[t as usize]);
        }
        true
    }

    /// The normals of the triangles that can hold the closest point of a point of the box: the
    /// gradient there is one of them, or lies between those of the triangles meeting at the
    /// closest edge or vertex — the same hull [`MeshDistance::gradient_bounds`] bounds.
    fn gradient_generators(&self, lo: &[f64], hi: &[f64], out: &mut Vec<f64>) -> bool {
        if !self.check.is_closed_manifold() {
            return false;
        }
        for &t in self.candidates(lo, hi).iter() {
            out.extend_from_slice(&self.normals[t as usize]);
        }
        true
    }
}

/// The whole module's tests (readers, winding numbers, distances, enclosures) live here, as a child
/// of the distance, because most of them look at its private state (the pseudonormals, the sides).
#[cfg(test)]
#[path = "tests.rs"]
mod tests;
