//! Writes the model a `validate_generated` fuzz input builds (`fuzz/corpus/validate_generated/…`,
//! `fuzz/artifacts/validate_generated/…`) as pretty ISM JSON, to reproduce a finding with `ism`:
//! `cargo run -p ism-conformance --example generated_model -- INPUT > model.ism.json`.

use ism_conformance::fuzz::generated::Generated;
use ism_format::io::{self, WriteOptions};
use ism_format::Encoding;

fn main() {
    let path = std::env::args()
        .nth(1)
        .expect("usage: generated_model INPUT");
    let bytes = std::fs::read(&path).expect("read the input");
    let g = Generated::from_bytes(&bytes).expect("the bytes build a model");
    let options = WriteOptions {
        pretty: true,
        ..WriteOptions::default()
    };
    let text = io::to_vec(&g.model, Encoding::Json, options).expect("encode");
    println!("{}", String::from_utf8_lossy(&text));
}
