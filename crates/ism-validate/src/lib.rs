//! ISM validator: structure, invariance and certified positivity of every stage
#![deny(missing_docs)]
