//! `ism fit --mesh`'s OBJ and glTF/GLB readers (`ism_export::obj::read_obj`,
//! `ism_export::gltf::read_gltf`, with `ism_fit`'s welding) on arbitrary bytes (property in
//! `ism_conformance::fuzz::fit_mesh`).
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| ism_conformance::fuzz::fit_mesh(data));
