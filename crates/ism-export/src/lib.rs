//! ISM curved-surface extraction and converters: OBJ, glTF 2.0, VTK; mesh import.
//!
//! - [`extract`]: the shape `O = F⁻¹(c)` as a welded, outward-oriented triangle mesh (3D) or
//!   polyline (2D): each linear patch `θ_σ` refined to a chordal `tolerance` and mapped through the
//!   stage inverses; same components and Euler characteristic as the linear isocomplex.
//! - [`marching`]: the linear isocomplex itself (marching triangles / tetrahedra), the topology
//!   reference and cost baseline.
//! - [`mesh`]: the [`Mesh`] type and its [`Topology`](mesh::Topology) summary.
//! - Writers streaming to any `impl Write`: [`obj`], [`gltf`] (`.gltf`/`.glb` via `gltf-json`),
//!   [`vtk`] (legacy `.vtk` and XML `.vtu`); [`format`](mod@format) picks one from a file name.
//! - [`volume`]: the complex with `F` as VTK Bézier cells (exact for one polynomial stage).
//! - [`import`]: `.vtu` / `.vtk` / `.msh` simplicial meshes with a point field → linear ISM.
//! - Triangle-mesh readers beside their writers, for `ism fit --mesh`: [`obj::read_obj`],
//!   [`gltf::read_gltf`] (errors: [`MeshReadError`]).
//!
//! ```
//! use ism_export::{extract::{extract, ExtractOptions}, format::{write_mesh, ExportFormat}, marching::marching};
//! use ism_format::builder::{ModelBuilder, StageBuilder};
//! use ism_geom::ModelEval;
//!
//! // A square of two triangles with one corner inside; a quadratic stage bends the diagonal.
//! let model = ModelBuilder::new(2)
//!     .vertex(&[0.0, 0.0], -1.0)
//!     .vertex(&[1.0, 0.0], 1.0)
//!     .vertex(&[1.0, 1.0], 1.0)
//!     .vertex(&[0.0, 1.0], 1.0)
//!     .simplex(&[0, 1, 2])
//!     .simplex(&[0, 2, 3])
//!     .stage(StageBuilder::bezier(2).face(&[0, 2], &[0.7, 0.3], &[]).build())
//!     .build()?;
//! let eval = ModelEval::new(&model)?;
//! let (curve, report) = extract(&eval, &ExtractOptions { tolerance: 1e-4, max_depth: 10 })?;
//! let linear = marching(&model)?;
//! // Same topology as the linear isocomplex (one open arc), more vertices, all on F = c.
//! assert_eq!(curve.topology().components, linear.topology().components);
//! assert_eq!(curve.topology().euler_characteristic, 1);
//! assert!(curve.num_vertices() > linear.num_vertices() && report.max_residual < 1e-12);
//! for p in &curve.positions {
//!     assert!(eval.value(&p[..2]).unwrap().abs() < 1e-9);
//! }
//! // Stream it out, and read the OBJ back.
//! let mut obj = Vec::new();
//! write_mesh(&curve, ExportFormat::Obj, Some("arc"), &mut obj)?;
//! let text = String::from_utf8(obj).unwrap();
//! assert_eq!(text.lines().filter(|l| l.starts_with("l ")).count(), curve.num_cells());
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
#![deny(missing_docs)]

pub mod error;
pub mod export;
pub mod extract;
pub mod format;
pub mod gltf;
pub mod import;
pub mod marching;
pub mod mesh;
pub mod obj;
pub mod volume;
pub mod vtk;
mod vtu_data;

pub use error::{Error, MeshReadError, Result};
pub use mesh::Mesh;
