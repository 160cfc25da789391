//! Fitting policy for a mesh, decided here from the mesh itself so that every caller (`ism fit
//! --mesh`, the Python package's `fit_mesh`) fits the same way and only renders the decisions:
//! refuse a mesh that is not a closed manifold, take the domain (given, or the bounding box padded
//! by a margin of the diagonal), switch the Plantinga–Vegter topology phase off where the sharpest
//! edge says it cannot pass ([`PV_SHARPEST_EDGE`]), bound its smallest cell, and name the topology
//! the fit must reproduce.

use super::{MeshCheck, MeshDistance, PV_SHARPEST_EDGE};
use crate::FitOptions;

/// Why a mesh fit is refused before it starts (the callers put their own words around it: the
/// mesh's name, their option's name).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum MeshPlanError {
    /// Not a closed, consistently oriented manifold: [`MeshDistance::refusal`]'s reason.
    #[error("{0}")]
    NotClosedManifold(String),
    /// A domain given with another count of numbers than 6.
    #[error("a mesh's domain needs 6 numbers, got {0}")]
    DomainLength(usize),
}

/// The decisions of a mesh fit ([`MeshDistance::plan`]).
#[derive(Clone, Debug, PartialEq)]
pub struct MeshPlan {
    /// The fitting domain, `x0,x1,y0,y1,z0,z1`.
    pub domain: Vec<f64>,
    /// Whether the Plantinga–Vegter phase runs: asked for, and no edge sharper than
    /// [`PV_SHARPEST_EDGE`] (at such a crease the test fails at every cell size).
    pub topology_phase: bool,
    /// The sharpest edge's normal turn (radians) when it switched off a phase that was asked for
    /// (callers warn with it); `None` otherwise.
    pub skipped_for_sharp_edge: Option<f64>,
    /// Whether the mesh faced inward and is fitted reversed ([`MeshDistance::flipped`]).
    pub flipped: bool,
    /// The mesh's combinatorial check; its components and Euler characteristic are the topology
    /// the fit must reproduce ([`MeshPlan::expected_topology`]).
    pub check: MeshCheck,
    /// Length of the mesh's bounding-box diagonal (distances are also reported relative to it).
    pub diagonal: f64,
    /// Median length of the mesh's edges: half of it bounds the phase's smallest cell.
    pub median_edge: f64,
}

impl MeshPlan {
    /// `(components, Euler characteristic)` the fit must have: the mesh's (a plan exists only for a
    /// closed manifold, whose topology is that of the solid's boundary).
    pub fn expected_topology(&self) -> (usize, i64) {
        (self.check.components, self.check.euler)
    }

    /// Sets the options the plan decides: the topology phase on or off, and its smallest cell —
    /// half the median mesh edge or the tolerance, whichever is larger (below that the phase can
    /// only find the creases, not features the mesh has; the topology is checked against the
    /// mesh's afterwards). Call it after the tolerance is set.
    pub fn apply(&self, options: &mut FitOptions) {
        options.topology = self.topology_phase;
        options.pv_min_edge = (0.5 * self.median_edge).max(options.tolerance);
    }
}

impl MeshDistance {
    /// The decisions of a fit of this mesh: `domain` if given (6 numbers) or the bounding box
    /// padded by `margin × diagonal`; `topology` says whether the caller asks for the
    /// Plantinga–Vegter phase.
    ///
    /// # Errors
    /// [`MeshPlanError::NotClosedManifold`] first (the signed distance of an open mesh jumps, no
    /// fit can meet it), then [`MeshPlanError::DomainLength`].
    pub fn plan(
        &self,
        domain: Option<&[f64]>,
        margin: f64,
        topology: bool,
    ) -> Result<MeshPlan, MeshPlanError> {
        if let Some(why) = self.refusal() {
            return Err(MeshPlanError::NotClosedManifold(why));
        }
        let domain = match domain {
            Some(d) if d.len() != 6 => return Err(MeshPlanError::DomainLength(d.len())),
            Some(d) => d.to_vec(),
            None => self.mesh().domain(margin),
        };
        let sharpest = self.sharpest_edge();
        let sharp = sharpest > PV_SHARPEST_EDGE;
        Ok(MeshPlan {
            domain,
            topology_phase: topology && !sharp,
            skipped_for_sharp_edge: (topology && sharp).then_some(sharpest),
            flipped: self.flipped(),
            check: self.check(),
            diagonal: self.mesh().diagonal(),
            median_edge: self.mesh().median_edge_length(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::super::TriangleMesh;
    use super::*;

    /// The decisions against what the mesh is: an icosphere (smooth, edges turn by ~15.9° at level
    /// 2: 2·asin of half the edge over the radius) keeps the phase, a tetrahedron (edges turn by
    /// 180° − 70.53°) loses it, an inside-out mesh is flipped, an open one refused.
    #[test]
    fn plans_follow_the_mesh() {
        let sphere = MeshDistance::new(TriangleMesh::icosphere(2, 1.0, [0.0; 3])).unwrap();
        let plan = sphere.plan(None, 0.05, true).unwrap();
        assert!(plan.topology_phase && plan.skipped_for_sharp_edge.is_none());
        assert_eq!(plan.expected_topology(), (1, 2));
        assert!(!plan.flipped);
        // The box padded by 5% of its diagonal on each side.
        let pad = 0.05 * plan.diagonal;
        let (lo, hi) = sphere.mesh().bounding_box();
        assert_eq!(
            plan.domain,
            vec![
                lo[0] - pad,
                hi[0] + pad,
                lo[1] - pad,
                hi[1] + pad,
                lo[2] - pad,
                hi[2] + pad
            ]
        );
        assert!(!sphere.plan(None, 0.05, false).unwrap().topology_phase);
        let given = [-2.0, 2.0, -2.0, 2.0, -2.0, 2.0];
        assert_eq!(
            sphere.plan(Some(&given), 0.05, true).unwrap().domain,
            given.to_vec()
        );
        assert_eq!(
            sphere.plan(Some(&given[..4]), 0.05, true),
            Err(MeshPlanError::DomainLength(4))
        );
        let mut options = FitOptions::new(&plan.domain);
        options.tolerance = 1e-9;
        plan.apply(&mut options);
        assert!(options.topology && options.pv_min_edge == 0.5 * plan.median_edge);

        let tet = TriangleMesh {
            positions: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            triangles: vec![[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]],
        };
        let inside_out = MeshDistance::new(tet.clone()).unwrap();
        let plan = inside_out.plan(None, 0.0, true).unwrap();
        assert!(plan.flipped && !plan.topology_phase);
        let turn = plan.skipped_for_sharp_edge.unwrap();
        assert!(turn > PV_SHARPEST_EDGE && turn < std::f64::consts::PI);
        let mut options = FitOptions::new(&plan.domain);
        plan.apply(&mut options);
        assert!(!options.topology);

        let open = TriangleMesh {
            triangles: tet.triangles[..3].to_vec(),
            ..tet
        };
        let open = MeshDistance::new(open).unwrap();
        assert!(matches!(
            open.plan(Some(&given[..4]), 0.0, true),
            Err(MeshPlanError::NotClosedManifold(_))
        ));
    }
}
