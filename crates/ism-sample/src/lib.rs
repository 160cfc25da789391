//! ISM sampler: exact surface, volume and near-surface point sets; point queries
#![deny(missing_docs)]
