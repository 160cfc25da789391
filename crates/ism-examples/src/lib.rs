//! ISM example and benchmark models: the papers' shapes and generated large complexes
#![deny(missing_docs)]
