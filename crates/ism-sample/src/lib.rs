//! ISM sampler: exact point sets from the curved shape of an Iso-Simplicial Model, and point
//! queries.
//!
//! - [`Sampler::surface`]: points on `O = F⁻¹(c)` distributed uniformly by TRUE curved area (length
//!   in 2D), by rejection against certified per-region bounds of the parametric map's area
//!   element ([`chain`], [`bound`], [`surface`]), with unit normals and source simplex ids; every point meets
//!   `|F − c| ≤ 1e-10 · |∇F| · L`.
//! - [`Sampler::volume`]: uniform in `|K|` or a box, with `F` and the inside label;
//!   [`Sampler::near_surface`]: surface points displaced along random directions by `N(0, σ²)`.
//! - [`Sampler::query`]: containing simplex, `F`, sign and `∇F` at given points ([`points`] reads
//!   them from CSV or NPY).
//! - Output streams block by block into a [`Sink`]: [`FormatWriter`] writes PLY (binary
//!   little-endian or ASCII), CSV or NPY; [`Collect`] keeps rows in memory.
//! - Reproducible: per-chunk ChaCha streams ([`seed`]) make a seed's output bit-identical for any
//!   thread count.
//!
//! ```
//! use ism_format::builder::{ModelBuilder, StageBuilder};
//! use ism_sample::{Collect, FormatWriter, OutputFormat, Sampler, Sink};
//!
//! // A square of two triangles, one corner inside, with a quadratic stage bending the curve.
//! let model = ModelBuilder::new(2)
//!     .vertex(&[0.0, 0.0], -1.0)
//!     .vertex(&[1.0, 0.0], 1.0)
//!     .vertex(&[1.0, 1.0], 1.0)
//!     .vertex(&[0.0, 1.0], 1.0)
//!     .simplex(&[0, 1, 2])
//!     .simplex(&[0, 2, 3])
//!     .stage(StageBuilder::bezier(2).face(&[0, 2], &[0.7, 0.3], &[]).build())
//!     .build()?;
//! let sampler = Sampler::new(&model)?.seed(7);
//! let mut rows = Collect::default();
//! sampler.surface(100, &mut rows)?;
//! assert_eq!(rows.rows.positions.len(), 200);
//! // Every point is on the curve F = 0 (within 1e-10 of |∇F| times the model size).
//! assert!(rows.rows.values.iter().all(|f| f.abs() < 1e-9));
//!
//! // The same run written as CSV.
//! let mut csv = FormatWriter::new(Vec::new(), OutputFormat::Csv);
//! sampler.surface(3, &mut csv)?;
//! let text = String::from_utf8(csv.into_inner()).unwrap();
//! assert!(text.starts_with("x,y,nx,ny,f,simplex\n"));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
#![deny(missing_docs)]

mod affine;
pub mod bound;
pub mod chain;
pub mod error;
mod flat;
mod homothety;
pub mod output;
pub mod points;
pub mod sampler;
pub mod seed;
pub mod surface;

pub use error::{Result, SampleError};
pub use output::{Collect, Column, FormatWriter, Header, OutputFormat, SampleBlock, Sink};
pub use sampler::{Progress, Region, Sampler};
pub use surface::{SurfacePoint, SurfaceTable, Weighting, SURFACE_TOLERANCE};
