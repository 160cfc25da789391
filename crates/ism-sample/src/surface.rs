//! Points on the shape `O`, uniform by true curved area (length in 2D).
//!
//! 1. Per top simplex σ crossed by the level, the linear patch `θ_σ` (segment, triangle or quad),
//!    its point-space area `A_σ` and a certified bound `B_σ ≥ J` of the area element of the
//!    parametric map `θ_σ → O ∩ σ` ([`crate::bound`]).
//! 2. Choose σ with probability `A_σ B_σ / Σ A B`, `u` uniform on `θ_σ`, map `w = X⁻¹(u)`,
//!    `p = W(w)`, and accept with probability `J(u) / B_σ`. The accepted points have density
//!    `∝ J`, i.e. uniform with respect to the curved area; `J > B_σ` is reported as an error, never
//!    clipped.
//! 3. Every accepted point is checked against `|F(p) − c| ≤ SURFACE_TOLERANCE · |∇F(p)| · L`
//!    (`L` the diagonal of the model's bounding box) and polished by Newton steps along `∇F`
//!    inside its simplex if needed.

use ism_format::Model;
use ism_geom::{linalg, Bary, Mat, ModelEval, MAX_VARS};
use rand::Rng;
use rayon::prelude::*;

use crate::bound::area_element_bound;
use crate::error::{Result, SampleError};

/// Required closeness of a surface sample to `O`, relative to the model size: `|F − c| / |∇F|`
/// (the first-order distance to the level set) at most this times the bounding-box diagonal. The
/// inverse map converges to `1e-12` in barycentric coordinates, which keeps samples two orders
/// inside this; the Newton polish handles the rare point where `|∇F|` is small.
pub const SURFACE_TOLERANCE: f64 = 1e-10;

/// Largest accepted residual `|X(w) − u|∞` of the inverse map. The kernel aims at `1e-12` and may
/// stall just above it on strongly weighted rational stages; a residual of `1e-9` moves the point
/// by `1e-9` of the simplex size in parameter space, which changes the sampled density by a
/// relative `O(1e-9)` (far below what any statistical test resolves), and the surface tolerance
/// below is checked (and polished) on the final point anyway.
pub const INVERSE_RESIDUAL: f64 = 1e-9;

/// Newton steps along `∇F` tried when a sample misses [`SURFACE_TOLERANCE`].
const POLISH_STEPS: usize = 4;

/// How patches are weighted and points accepted.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Weighting {
    /// Uniform by true curved area (the default and the only correct choice).
    #[default]
    CurvedArea,
    /// Uniform by the area of the linear patches, then mapped: NOT uniform on the curved shape.
    /// Kept so that the uniformity tests can show they reject it; do not use it for data.
    LinearArea,
}

/// One patch of the surface table.
#[derive(Clone, Debug)]
pub struct PatchEntry {
    /// Top simplex id.
    pub simplex: u32,
    /// Barycentric corners of up to two triangles (3D) or one segment (2D, first two used).
    corners: [[Bary; 3]; 2],
    /// Number of triangles (0 for a segment, 1 or 2).
    triangles: u8,
    /// Fraction of the patch area in the first triangle.
    first_fraction: f64,
    /// Point-space area (length in 2D) of the linear patch.
    pub linear_area: f64,
    /// Certified bound of the area element on this simplex.
    pub bound: f64,
    /// `|∇F_lin|` on this simplex.
    linear_gradient: f64,
}

/// Everything the surface sampler precomputes: one entry per crossed simplex and the cumulative
/// selection weights.
#[derive(Clone, Debug)]
pub struct SurfaceTable {
    /// The patches, in simplex order.
    pub patches: Vec<PatchEntry>,
    cumulative: Vec<f64>,
    /// `Σ A_σ B_σ`: an upper bound of the curved area of `O`.
    pub bounded_area: f64,
    /// `Σ A_σ`: the area of the linear isocomplex.
    pub linear_area: f64,
    scale: f64,
    weighting: Weighting,
}

/// Edge matrix `E[x][l] = (v_{l+1} − v_0)_x`.
pub(crate) fn edge_matrix(model: &Model, s: usize) -> Mat {
    let n = model.dim();
    let ids = model.simplex(s);
    let v0 = model.vertex(ids[0] as usize);
    let mut e = [[0.0; MAX_VARS]; MAX_VARS];
    for l in 0..n {
        let v = model.vertex(ids[l + 1] as usize);
        for x in 0..n {
            e[x][l] = v[x] - v0[x];
        }
    }
    e
}

/// Diagonal of the model's bounding box (1 for an empty model).
pub(crate) fn model_scale(model: &Model) -> f64 {
    let n = model.dim();
    if model.vertices.is_empty() || n == 0 {
        return 1.0;
    }
    let mut d2 = 0.0;
    for x in 0..n {
        let coords = model.vertices.iter().skip(x).step_by(n);
        let (lo, hi) = coords.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
        d2 += (hi - lo).powi(2);
    }
    if d2 > 0.0 {
        d2.sqrt()
    } else {
        1.0
    }
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

fn sub3(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross_norm(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    norm(&[
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ])
}

impl SurfaceTable {
    /// Builds the table (in parallel over simplices).
    ///
    /// # Errors
    /// [`SampleError::EmptySurface`] when no simplex is crossed; [`SampleError::Uncertified`] when a
    /// stage's area-element bound cannot be certified on a crossed simplex.
    pub fn new(eval: &ModelEval, weighting: Weighting) -> Result<SurfaceTable> {
        let model = eval.model();
        let n = model.dim();
        let patches: Vec<PatchEntry> = (0..eval.num_simplices())
            .into_par_iter()
            .filter_map(|s| eval.patch(s).map(|p| (s, p)))
            .map(|(s, patch)| {
                let e = edge_matrix(model, s);
                let inv = linalg::inverse(n, &e).ok_or_else(|| SampleError::Numerical {
                    simplex: s,
                    reason: "degenerate simplex".into(),
                })?;
                let ids = model.simplex(s);
                let f0 = model.values[ids[0] as usize];
                let mut g = [0.0; 3];
                for (x, gx) in g.iter_mut().enumerate().take(n) {
                    *gx = (0..n)
                        .map(|l| (model.values[ids[l + 1] as usize] - f0) * inv[l][x])
                        .sum();
                }
                let corners: Vec<Bary> = patch.corners.iter().map(|c| c.u).collect();
                let pts: Vec<[f64; 3]> = corners.iter().map(|u| eval.point(s, u)).collect();
                let (tris, count, first_fraction, area) = if n == 2 {
                    let len = norm(&sub3(&pts[1], &pts[0]));
                    ([[corners[0], corners[1], corners[1]]; 2], 0u8, 1.0, len)
                } else {
                    let a0 = 0.5 * cross_norm(&sub3(&pts[1], &pts[0]), &sub3(&pts[2], &pts[0]));
                    if corners.len() == 4 {
                        let a1 = 0.5 * cross_norm(&sub3(&pts[2], &pts[0]), &sub3(&pts[3], &pts[0]));
                        let t = [
                            [corners[0], corners[1], corners[2]],
                            [corners[0], corners[2], corners[3]],
                        ];
                        (t, 2u8, a0 / (a0 + a1), a0 + a1)
                    } else {
                        let t = [corners[0], corners[1], corners[2]];
                        ([t, t], 1u8, 1.0, a0)
                    }
                };
                let bound =
                    area_element_bound(eval.local_map(s), &e).map_err(|(stage, reason)| {
                        SampleError::Uncertified {
                            simplex: s,
                            stage,
                            reason,
                        }
                    })?;
                Ok(PatchEntry {
                    simplex: s as u32,
                    corners: tris,
                    triangles: count,
                    first_fraction,
                    linear_area: area,
                    bound,
                    linear_gradient: norm(&g),
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let patches: Vec<PatchEntry> = patches
            .into_iter()
            .filter(|p| p.linear_area > 0.0)
            .collect();
        if patches.is_empty() {
            return Err(SampleError::EmptySurface { level: model.level });
        }
        // Sequential prefix sums: the same table, bit for bit, whatever the thread count.
        let mut cumulative = Vec::with_capacity(patches.len());
        let mut acc = 0.0;
        let mut linear = 0.0;
        for p in &patches {
            acc += match weighting {
                Weighting::CurvedArea => p.linear_area * p.bound,
                Weighting::LinearArea => p.linear_area,
            };
            linear += p.linear_area;
            cumulative.push(acc);
        }
        Ok(SurfaceTable {
            patches,
            cumulative,
            bounded_area: acc,
            linear_area: linear,
            scale: model_scale(model),
            weighting,
        })
    }

    /// Number of patches (crossed simplices).
    pub fn len(&self) -> usize {
        self.patches.len()
    }

    /// Whether there are no patches (never true for a built table).
    pub fn is_empty(&self) -> bool {
        self.patches.is_empty()
    }

    fn pick(&self, rng: &mut impl Rng) -> &PatchEntry {
        let x = rng.random::<f64>() * self.bounded_area;
        let i = self
            .cumulative
            .partition_point(|&c| c <= x)
            .min(self.patches.len() - 1);
        &self.patches[i]
    }

    /// Draws one accepted surface sample.
    ///
    /// # Errors
    /// [`SampleError::Numerical`] when the inverse map does not converge, the area element exceeds
    /// its certified bound, or the point cannot be brought within [`SURFACE_TOLERANCE`].
    pub fn draw(&self, eval: &ModelEval, rng: &mut impl Rng) -> Result<SurfacePoint> {
        let n = eval.dim();
        loop {
            let patch = self.pick(rng);
            let s = patch.simplex as usize;
            let u = uniform_on_patch(patch, rng);
            let map = eval.local_map(s);
            let (w, accept) = if map.stages().is_empty() {
                (u, true)
            } else {
                let inv = map.inverse(&u);
                if inv.residual.is_nan() || inv.residual > INVERSE_RESIDUAL {
                    return Err(SampleError::Numerical {
                        simplex: s,
                        reason: format!(
                            "inverse map did not converge at u = {:?} (residual {:e})",
                            &u[..=n],
                            inv.residual
                        ),
                    });
                }
                let accept = match self.weighting {
                    Weighting::LinearArea => true,
                    Weighting::CurvedArea => {
                        let j = self.area_element(eval, s, &inv.w, patch)?;
                        if j > patch.bound {
                            return Err(SampleError::Numerical {
                                simplex: s,
                                reason: format!(
                                    "area element {j} exceeds its certified bound {}",
                                    patch.bound
                                ),
                            });
                        }
                        rng.random::<f64>() * patch.bound < j
                    }
                };
                (inv.w, accept)
            };
            if accept {
                return self.finish(eval, s, w);
            }
        }
    }

    /// `J = |∇F| / (|∇F_lin| det DX)` at barycentric `w` of simplex `s` (module doc of
    /// [`crate::bound`]).
    fn area_element(
        &self,
        eval: &ModelEval,
        s: usize,
        w: &Bary,
        patch: &PatchEntry,
    ) -> Result<f64> {
        let n = eval.dim();
        let det = eval.local_map(s).det(w);
        let grad = eval
            .gradient_at(s, w)
            .ok_or_else(|| SampleError::Numerical {
                simplex: s,
                reason: "singular stage Jacobian".into(),
            })?;
        if det.is_nan() || det <= 0.0 {
            return Err(SampleError::Numerical {
                simplex: s,
                reason: format!("det DX = {det} ≤ 0 at w = {:?}", &w[..=n]),
            });
        }
        Ok(norm(&grad[..n]) / (patch.linear_gradient * det))
    }

    fn finish(&self, eval: &ModelEval, s: usize, mut w: Bary) -> Result<SurfacePoint> {
        let n = eval.dim();
        let c = eval.model().level;
        for step in 0..=POLISH_STEPS {
            let f = eval.value_at(s, &w);
            let grad = eval
                .gradient_at(s, &w)
                .ok_or_else(|| SampleError::Numerical {
                    simplex: s,
                    reason: "singular stage Jacobian".into(),
                })?;
            let gn = norm(&grad[..n]);
            let p = eval.point(s, &w);
            if (f - c).abs() <= SURFACE_TOLERANCE * gn * self.scale {
                let mut normal = [0.0; 3];
                for x in 0..n {
                    normal[x] = grad[x] / gn;
                }
                return Ok(SurfacePoint {
                    p,
                    normal,
                    value: f,
                    simplex: s,
                });
            }
            if step == POLISH_STEPS || gn == 0.0 {
                break;
            }
            // Newton along ∇F, kept in the simplex (the shape crosses σ, so the step is short).
            let mut q = p;
            for x in 0..n {
                q[x] -= (f - c) * grad[x] / (gn * gn);
            }
            w = ism_geom::stage::project(n + 1, &eval.barycentric(s, &q));
        }
        Err(SampleError::Numerical {
            simplex: s,
            reason: format!("sample at w = {:?} misses |F − c| ≤ {SURFACE_TOLERANCE}·|∇F|·L after {POLISH_STEPS} Newton steps", &w[..=n]),
        })
    }
}

/// A point of `O` with its unit normal and source simplex.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    /// Position (first `n` entries).
    pub p: [f64; 3],
    /// `∇F/|∇F|` (first `n` entries): points outside.
    pub normal: [f64; 3],
    /// `F(p)` (equal to the level within tolerance).
    pub value: f64,
    /// Source top simplex.
    pub simplex: usize,
}

/// `u` uniform (by point-space area; `W` is affine so barycentric area is proportional) on the
/// patch.
fn uniform_on_patch(patch: &PatchEntry, rng: &mut impl Rng) -> Bary {
    let mut u = [0.0; MAX_VARS];
    if patch.triangles == 0 {
        let t: f64 = rng.random();
        let [a, b, _] = patch.corners[0];
        for i in 0..MAX_VARS {
            u[i] = (1.0 - t) * a[i] + t * b[i];
        }
        return u;
    }
    let which = if patch.triangles == 2 && rng.random::<f64>() >= patch.first_fraction {
        1
    } else {
        0
    };
    let [a, b, c] = patch.corners[which];
    let r1: f64 = rng.random();
    let r2: f64 = rng.random();
    let s = r1.sqrt();
    let (la, lb, lc) = (1.0 - s, s * (1.0 - r2), s * r2);
    for i in 0..MAX_VARS {
        u[i] = la * a[i] + lb * b[i] + lc * c[i];
    }
    u
}
