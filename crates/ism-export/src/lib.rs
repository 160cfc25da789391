//! ISM curved-surface extraction and converters: OBJ, glTF 2.0, VTK; mesh import
#![deny(missing_docs)]
