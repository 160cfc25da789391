//! Conservative interval arithmetic for the Plantinga–Vegter test: the kernel's
//! [`ism_geom::interval`], shared with the sampler's certified bounds.

pub use ism_geom::interval::*;
