//! Models shared by the integration tests of the binary encodings.

use ism_format::builder::{ModelBuilder, StageBuilder};
use ism_format::Model;

/// The model of spec Appendix A (whose compact bytes the spec lists).
pub fn appendix_a() -> Model {
    ModelBuilder::new(2)
        .name("t")
        .vertex(&[0.0, 0.0], -1.0)
        .vertex(&[1.0, 0.0], 1.0)
        .vertex(&[0.0, 1.0], 1.0)
        .simplex(&[0, 1, 2])
        .stage(
            StageBuilder::bezier(2)
                .face(&[1, 2], &[0.5, 0.5], &[])
                .build(),
        )
        .build()
        .unwrap()
}
