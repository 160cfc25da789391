//! Per-stage index of face records and expansion of one stage on one top simplex into its dense
//! control net (the storage rules of spec/ism-format.md §5.2, restated in spec/validation.md §4.1).

use ism_format::indexed::LocalFace;
use ism_format::{multi_index, IndexedModel, Model, Stage, StageKind};

use rayon::prelude::*;

use crate::certify::DenseNet;

/// Whether a stored point (positive coordinates on its face, summing to 1 within the ISM-202
/// tolerance) is in its open face in reduced coordinates, whichever vertex is dropped: the map uses
/// `(b₁ … bₙ)` and `b₀ = 1 − Σ`, so the dropped coordinate is really `1 − Σ_{i≠j} b_i`, which can be
/// 0 (or negative) although the stored `b_j > 0` — e.g. `(1e-17, 1.0)` puts an edge point on the
/// vertex, where det DX = 0. The theorems of spec/validation.md §4.2 apply only when every such
/// `1 − Σ_{i≠j} b_i` is `> 0`, decided exactly: the floating-point sum of positive numbers is within
/// `k·u` of the exact one, and only sums within that of 1 are summed exactly.
pub fn reduced_adjusted(point: &[f64]) -> bool {
    if point.len() < 2 {
        return point.iter().all(|&x| x > 0.0);
    }
    (0..point.len()).all(|j| {
        let others = point
            .iter()
            .enumerate()
            .filter(|&(i, _)| i != j)
            .map(|(_, &x)| x);
        let approx: f64 = others.clone().sum();
        // At most 3 positive terms: relative error ≤ 2u(1 + 2u); 8u is a wide margin.
        let margin = 8.0 * f64::EPSILON * approx.abs();
        if approx + margin < 1.0 {
            true
        } else if approx - margin >= 1.0 {
            false
        } else {
            let exact = others
                .filter_map(crate::exact::rational)
                .fold(num_rational::BigRational::from_integer(0.into()), |a, x| {
                    a + x
                });
            exact < num_rational::BigRational::from_integer(1.into())
        }
    })
}

/// A face key: sorted global vertex ids, padded with `u32::MAX`.
pub type FaceKey = [u32; 4];

/// Builds the key of a face from any order of its ids (at most 4).
pub fn face_key(ids: &[u32]) -> FaceKey {
    let mut k = [u32::MAX; 4];
    k[..ids.len()].copy_from_slice(ids);
    k[..ids.len()].sort_unstable();
    k
}

/// Face records of one Bézier or rational stage, found through the indexed model's topology and
/// stage table (no face key is hashed).
#[derive(Debug)]
pub struct StageIndex<'a> {
    model: &'a Model,
    stage: &'a Stage,
    /// The indexed model and the stage's index in it: the stage's face → record table (and, for a
    /// lazily indexed model, the topology's face tables) is built on first use, so stages decided
    /// by a theorem never build it.
    indexed: &'a IndexedModel,
    stage_index: usize,
    /// All local multi-indices of degree `d` in `n + 1` variables, flat.
    all: Vec<u32>,
    /// Per face size, the correctly rounded fixed points `J/d` of the owned multi-indices `J`.
    fixed_points: Vec<Vec<f64>>,
    /// Per record: every stored point stays in its open face in every simplex's reduced
    /// coordinates (see [`reduced_adjusted`]): the hypothesis of the theorems.
    adjusted: Vec<bool>,
}

/// Which faces of one top simplex carry records: `records[mask]` for the face made of the local
/// positions in `mask`.
#[derive(Clone, Copy, Debug, Default)]
pub struct SimplexRecords {
    /// Record index per local face mask (index 0 unused).
    pub records: [Option<usize>; 16],
}

impl SimplexRecords {
    /// `(mask, record)` for each recorded face.
    pub fn iter(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        self.records
            .iter()
            .enumerate()
            .filter_map(|(mask, r)| r.map(|r| (mask, r)))
    }

    /// Number of recorded faces.
    pub fn count(&self) -> usize {
        self.records.iter().filter(|r| r.is_some()).count()
    }
}

impl<'a> StageIndex<'a> {
    /// The face records of stage `k` of a (structurally checked) indexed model.
    pub fn new(indexed: &'a IndexedModel, k: usize) -> StageIndex<'a> {
        let model: &'a Model = indexed;
        let stage = &model.stages[k];
        let d = stage.degree;
        // The fixed points `J / d` per face size, computed once.
        let fixed_points: Vec<Vec<f64>> = (0..=model.dim() + 1)
            .map(|k1| {
                multi_index::owned(k1, d)
                    .iter()
                    .map(|&j| f64::from(j) / f64::from(d))
                    .collect()
            })
            .collect();
        let adjusted = (0..stage.faces.len())
            .into_par_iter()
            .map(|r| {
                let rec = stage.faces.record(r);
                let k1 = rec.face.len();
                k1 == 0 || rec.points.chunks(k1).all(reduced_adjusted)
            })
            .collect();
        StageIndex {
            model,
            stage,
            indexed,
            stage_index: k,
            adjusted,
            all: multi_index::all(model.dim() + 1, d),
            fixed_points,
        }
    }

    /// The stage.
    pub fn stage(&self) -> &Stage {
        self.stage
    }

    /// Whether record `r` stores exactly the fixed points (each coordinate the f64 nearest `J_j/d`).
    pub fn is_fixed(&self, r: usize) -> bool {
        // A few comparisons: decided when asked (only rational stages ask), not stored per record.
        let rec = self.stage.faces.record(r);
        self.fixed_points
            .get(rec.face.len())
            .is_some_and(|f| f.iter().zip(rec.points).all(|(&j, &x)| x == j))
    }

    /// Whether record `r` keeps every point in its open face whichever of its vertices a simplex
    /// drops in reduced coordinates (the theorems' "adjusted" hypothesis).
    pub fn is_adjusted(&self, r: usize) -> bool {
        self.adjusted[r]
    }

    /// Whether record `r` is a vertex record storing the vertex itself (`[1.0]`), which moves
    /// nothing.
    pub fn is_trivial(&self, r: usize) -> bool {
        let rec = self.stage.faces.record(r);
        rec.face.len() == 1 && rec.points.iter().all(|&x| x == 1.0)
    }

    /// The recorded faces of top simplex `s`.
    pub fn records(&self, s: usize) -> SimplexRecords {
        let m = self.model.dim() + 1;
        let mut out = SimplexRecords::default();
        let table = self.indexed.stage(self.stage_index);
        let faces = self.indexed.topology().faces_by_mask(self.model, s);
        for (record, &face) in out.records.iter_mut().zip(&faces).take(1 << m).skip(1) {
            *record = table.record_of(face);
        }
        out
    }

    /// The dense control net of this stage on top simplex `s`, in the simplex's stored vertex order.
    pub fn dense_net(&self, s: usize, records: &SimplexRecords) -> DenseNet {
        let ids = self.model.simplex(s);
        let m = ids.len();
        let d = self.stage.degree;
        let rational = self.stage.kind == StageKind::Rational;
        let count = self.all.len() / m;
        let mut points = Vec::with_capacity(count);
        let mut weights = if rational {
            Vec::with_capacity(count)
        } else {
            Vec::new()
        };
        let mut shifted = [0u32; 4];
        for idx in self.all.chunks(m) {
            let mut mask = 0usize;
            for (i, &e) in idx.iter().enumerate() {
                if e > 0 {
                    mask |= 1 << i;
                }
            }
            let mut p = [0.0; 4];
            let mut w = 1.0;
            match records.records[mask] {
                None => {
                    for (c, &e) in p.iter_mut().zip(idx) {
                        *c = f64::from(e) / f64::from(d);
                    }
                }
                Some(r) => {
                    let rec = self.stage.faces.record(r);
                    // Local positions of the face, ordered by global id: t_0 < … < t_k.
                    let face = LocalFace::of_mask(ids, mask as u8);
                    let pos = face.positions();
                    let k1 = pos.len();
                    for j in 0..k1 {
                        shifted[j] = idx[usize::from(pos[j])] - 1;
                    }
                    let rank = multi_index::rank(&shifted[..k1]);
                    for j in 0..k1 {
                        p[usize::from(pos[j])] = rec.points[rank * k1 + j];
                    }
                    if rational {
                        w = rec.weights[rank];
                    }
                }
            }
            points.push(p);
            if rational {
                weights.push(w);
            }
        }
        DenseNet {
            n: m - 1,
            degree: d,
            points,
            weights,
        }
    }
}
