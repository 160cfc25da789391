//! `ism fit --mesh`'s OBJ and glTF/GLB readers on arbitrary bytes (property in
//! `ism_conformance::fuzz::fit_mesh`).
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| ism_conformance::fuzz::fit_mesh(data));
