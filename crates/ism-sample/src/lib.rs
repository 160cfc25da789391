//! ISM sampler: exact surface, volume and near-surface point sets; point queries.
#![deny(missing_docs)]

pub mod error;
pub mod output;
pub mod points;
pub mod seed;

pub use error::{Result, SampleError};
pub use output::{Collect, Column, FormatWriter, Header, OutputFormat, SampleBlock, Sink};
pub mod bound;
