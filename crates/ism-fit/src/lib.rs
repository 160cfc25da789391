//! ISM fitting: adaptive polygonization of implicit functions, Hermite modeling, meshes in
#![deny(missing_docs)]
