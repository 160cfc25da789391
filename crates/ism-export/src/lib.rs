//! ISM curved-surface extraction and converters: OBJ, glTF 2.0, VTK; mesh import
#![deny(missing_docs)]

pub mod error;
pub mod extract;
pub mod format;
pub mod mesh;
pub mod obj;

pub use error::{Error, Result};
pub mod gltf;
pub mod import;
pub mod marching;
pub mod volume;
pub mod vtk;
