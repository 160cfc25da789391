//! ISM math kernel: Bernstein-Bezier on simplices, simplicial diffeomorphism stages, model evaluation
#![deny(missing_docs)]
