//! `ism import`'s mesh parsers (`.vtu`, legacy `.vtk`, `.msh`) on arbitrary bytes, each format in
//! turn: a typed error or a mesh; a mesh converts to a model `ism` reads back, or a typed error
//! (property in `ism_conformance::fuzz::import_mesh`).
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| ism_conformance::fuzz::import_mesh(data));
