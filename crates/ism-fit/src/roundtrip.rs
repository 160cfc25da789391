//! The check a fit passes before it is written: what the fitter produced must be what every
//! consumer reads. The model is encoded as `.ismb` and decoded bit-exactly; the exporter
//! (`ism-export`) extracts its curved shape, which must have the fit's topology and be a
//! consistently oriented manifold without degenerate cells; the sampler (`ism-sample`) draws
//! points on the shape, each within [`ism_sample::SURFACE_TOLERANCE`] of it. Library calls of the
//! same crates `ism export` and `ism sample` use, so a fit that passes here exports and samples.

use ism_format::model::Model;
use ism_geom::ModelEval;
use rand::SeedableRng;

use crate::isocontour::Topology;

/// What the round trip saw.
#[derive(Clone, Debug, PartialEq)]
pub struct RoundTrip {
    /// Bytes of the `.ismb` encoding.
    pub encoded_bytes: usize,
    /// Vertices of the extracted shape.
    pub mesh_vertices: usize,
    /// Triangles (3D) or segments (2D) of the extracted shape.
    pub mesh_cells: usize,
    /// Edges of the extracted shape on its boundary (where the shape meets the domain's box).
    pub boundary_edges: usize,
    /// Points the sampler drew on the shape.
    pub samples: usize,
}

/// The `roundTrip` member of `ism fit --json`.
pub fn to_json(r: &Result<RoundTrip, RoundTripError>) -> serde_json::Value {
    match r {
        Ok(t) => serde_json::json!({
            "ok": true,
            "encodedBytes": t.encoded_bytes,
            "exportedVertices": t.mesh_vertices,
            "exportedCells": t.mesh_cells,
            "exportedBoundaryEdges": t.boundary_edges,
            "samplesDrawn": t.samples,
        }),
        Err(e) => serde_json::json!({"ok": false, "error": ism_format::ErrorChain(e).to_string()}),
    }
}

/// Why a fit failed its round trip.
#[derive(Debug, thiserror::Error)]
pub enum RoundTripError {
    /// The model does not encode or decode.
    #[error("the model does not round-trip through .ismb")]
    Encoding(#[source] ism_format::Error),
    /// It decodes to something else.
    #[error("the model decoded from .ismb differs from the one encoded")]
    Differs,
    /// The kernel cannot evaluate it.
    #[error("the kernel cannot evaluate the model")]
    Eval(#[source] ism_geom::GeomError),
    /// The exporter fails on it.
    #[error("the exporter cannot extract the shape")]
    Export(#[source] ism_export::Error),
    /// The exported shape is not what the fit reports.
    #[error(
        "the exported shape has {components} component(s), χ = {euler}, {defects} defective \
         edges or cells; the fit has {expected_components} component(s), χ = {expected_euler}"
    )]
    Topology {
        /// Components of the exported shape.
        components: usize,
        /// Its Euler characteristic.
        euler: i64,
        /// Non-manifold edges, orientation conflicts and degenerate cells.
        defects: usize,
        /// The fit's components.
        expected_components: usize,
        /// The fit's Euler characteristic.
        expected_euler: i64,
    },
    /// The sampler fails on it.
    #[error("the sampler cannot draw on the shape")]
    Sample(#[source] ism_sample::SampleError),
}

/// Chordal tolerance of the extraction, as a fraction of the fit's tolerance.
const EXPORT_FRACTION: f64 = 0.25;

/// Points drawn by the sampler.
const SAMPLES: usize = 256;

/// Runs the round trip on `model`, whose shape should have `topology`; `tolerance` is the fit's.
///
/// # Errors
/// The first step that fails.
pub fn round_trip(
    model: &Model,
    topology: Topology,
    tolerance: f64,
) -> Result<RoundTrip, RoundTripError> {
    use ism_format::io::{self, Encoding, WriteOptions};
    let bytes = io::to_vec(model, Encoding::Binary, WriteOptions::default())
        .map_err(RoundTripError::Encoding)?;
    // A checked, indexed read: the evaluator shares its index (no copy, no second check).
    let decoded = io::from_slice_indexed(&bytes, &io::ReadOptions::default())
        .map_err(RoundTripError::Encoding)?
        .model;
    if decoded.model() != model {
        return Err(RoundTripError::Differs);
    }
    let eval = ModelEval::from_indexed(&decoded).map_err(RoundTripError::Eval)?;
    let options = ism_export::extract::ExtractOptions {
        tolerance: EXPORT_FRACTION * tolerance,
        ..Default::default()
    };
    let (mesh, _) =
        ism_export::extract::extract(&eval, &options).map_err(RoundTripError::Export)?;
    let t = mesh.topology();
    let defects = t.non_manifold_edges + t.orientation_conflicts + t.degenerate_cells;
    if t.components != topology.components
        || t.euler_characteristic != topology.euler
        || defects > 0
    {
        return Err(RoundTripError::Topology {
            components: t.components,
            euler: t.euler_characteristic,
            defects,
            expected_components: topology.components,
            expected_euler: topology.euler,
        });
    }
    let table = ism_sample::SurfaceTable::new(&eval, ism_sample::Weighting::CurvedArea)
        .map_err(RoundTripError::Sample)?;
    // A fixed seed: the check is reproducible.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(17);
    for _ in 0..SAMPLES {
        table
            .draw(&eval, &mut rng)
            .map_err(RoundTripError::Sample)?;
    }
    Ok(RoundTrip {
        encoded_bytes: bytes.len(),
        mesh_vertices: mesh.num_vertices(),
        mesh_cells: mesh.num_cells(),
        boundary_edges: t.boundary_edges,
        samples: SAMPLES,
    })
}
