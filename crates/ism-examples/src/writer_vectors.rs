//! Writer test vectors for `spec/vectors/writer/`: a model given as JSON text in any spelling
//! (`NAME.input.json`), and the exact bytes a conforming writer produces for it in every encoding
//! (spec §7.7): `NAME.ism.json` (compact), `NAME.pretty.ism.json`, `NAME.ism.msgpack`, `NAME.ismb`,
//! `NAME.ismc`, `NAME.isms`.
//!
//! The bytes come from the reference writer; `tests/python` rebuilds every one of them with a writer
//! written from the spec alone, so neither implementation is its own ground truth.

use std::path::{Path, PathBuf};

use ism_format::io::{self, WriteOptions};
use ism_format::Encoding;

/// One writer vector: its name and the input text.
#[derive(Clone, Debug)]
pub struct WriterVector {
    /// File stem.
    pub name: &'static str,
    /// The model as JSON text, deliberately not in canonical form.
    pub input: String,
}

/// The output forms of a writer vector: file suffix, encoding, and whether JSON is pretty.
pub const OUTPUTS: [(&str, Encoding, bool); 6] = [
    ("ism.json", Encoding::Json, false),
    ("pretty.ism.json", Encoding::Json, true),
    ("ism.msgpack", Encoding::MessagePack, false),
    ("ismb", Encoding::Binary, false),
    ("ismc", Encoding::Compact, false),
    ("isms", Encoding::Structured, false),
];

/// `levels` nested arrays around `0`, as JSON text with spaces.
fn nested(levels: usize) -> String {
    format!("{}0{}", "[ ".repeat(levels), " ]".repeat(levels))
}

/// Every writer vector, in a fixed order.
pub fn writer_vectors() -> Vec<WriterVector> {
    let triangle = r#""vertices": [0, 0, 1.5E0, 0, 0, 2.5e-5], "simplices": [0, 1, 2]"#;
    vec![
        WriterVector {
            name: "numbers",
            // Spellings of the input are not canonical; the outputs are (spec §7.7 table).
            input: format!(
                r#"{{"dimension": 2, "version": "1.0", {triangle},
  "values": [-1e-6, 1E16, 123456789012345678], "level": -0.0,
  "extras": {{
    "floats": [0.00001, 1e-5, 0.000001, 1e15, 1e+16, 15e15, -0.0, 0.0, 4.9e-324,
               1.7976931348623157e308, 0.1, 2.50, -1.5e-10, 1e21, 12345e-9, 100.0,
               0.30000000000000004, 1.0, 123456789.125, 9007199254740993.0],
    "integers": [0, -0, 1, -1, 127, 128, 255, 256, 65535, 65536, 4294967295, 4294967296,
                 -32, -33, -128, -129, -32768, -32769, -2147483648, -2147483649,
                 9223372036854775807, 18446744073709551615, -9223372036854775808]
  }}
}}"#
            ),
        },
        WriterVector {
            name: "strings-and-order",
            input: format!(
                r#"{{"version": "1.0", "dimension": 2, {triangle}, "values": [-1, 1, 1],
  "metadata": {{"description": "\b\f\n\r\t\u0001\u001f\u007f", "units": "mm",
    "name": "tab\there \"q\" \\ \/ \u00e9 \ud83d\ude00 \u2028 ü"}},
  "extensionsUsed": ["EXT_b", "EXT_ü", "EXT_a"],
  "extensions": {{"EXT_ü": {{"z": 1, "a": []}}, "EXT_b": {{}}, "EXT_a": null}},
  "extras": {{"z": "last key first", "a": {{"y": true, "b": false, "m": null}}}}
}}"#
            ),
        },
        WriterVector {
            name: "stages",
            input: r#"{"version": "1.0", "dimension": 2,
  "vertices": [0, 0, 1, 0, 1, 1, 0, 1], "simplices": [0, 1, 2, 0, 2, 3],
  "values": [-1, 1, 2, 0.5], "level": 0.25,
  "stages": [
    {"kind": "bezier", "degree": 2, "name": "bend", "faces": [{"face": [0, 2], "points": [0.6, 0.4]}],
     "extras": {"note": "stage extras"}},
    {"kind": "rational", "degree": 3, "faces": [{"face": [0, 1, 2], "points": [0.2, 0.3, 0.5], "weights": [2]},
                                                 {"face": [1], "points": [1], "weights": [0.5]}]},
    {"kind": "monotonic", "degree": 2, "direction": "parametric",
     "vertexMaps": [{"coefficients": [0, 0.25, 1], "vertex": 3}]},
    {"degree": 1, "kind": "bezier", "direction": "implicit", "faces": [], "vertexMaps": []}
  ]
}"#
            .into(),
        },
        WriterVector {
            name: "newer-minor",
            // A 1.0 writer writes 1.0, without the members of 1.1 it does not know (spec §8.1).
            input: format!(
                r#"{{"version": "1.1", "dimension": 2, {triangle}, "values": [-1, 1, 1],
  "addedIn11": {{"meaning": ["unknown", "to", 1.0]}}, "stages": [{{"kind": "bezier", "degree": 1, "alsoNew": 7}}]
}}"#
            ),
        },
        WriterVector {
            name: "deepest",
            // Nested to the limit of spec §7.8 and no further: level 64 in the model's and a
            // stage's extras.
            input: format!(
                r#"{{"version": "1.0", "dimension": 2, {triangle}, "values": [-1, 1, 1],
  "stages": [{{"kind": "bezier", "degree": 1, "extras": {}}}],
  "extras": {}
}}"#,
                nested(ism_format::MAX_DEPTH - 3),
                nested(ism_format::MAX_DEPTH - 1)
            ),
        },
        WriterVector {
            name: "structured",
            // The structured encoding's choices (spec §7.4.3): records by the complex at the
            // smallest lattice width (1; a vertex record and a triangle record; 2 for 2^-16),
            // f64 for a -0.0 coordinate, listed records when they are out of mask order, and a
            // monotonic stage by the complex with no records.
            input: r#"{"version": "1.0", "dimension": 2,
  "vertices": [0, 0, 1, 0, 1, 1, 0, 1, 2, 0], "simplices": [0, 1, 2, 0, 2, 3, 1, 4, 2],
  "values": [-1, 1, 2, 0.5, 1],
  "stages": [
    {"kind": "bezier", "degree": 3, "faces": [{"face": [0, 2], "points": [0.75, 0.25, 0.25, 0.75]},
      {"face": [1, 2], "points": [0.5, 0.5, 0.25, 0.75]}, {"face": [0, 1, 2], "points": [0.25, 0.5, 0.25]}]},
    {"kind": "rational", "degree": 2, "faces": [{"face": [2], "points": [1], "weights": [2]},
      {"face": [1, 4], "points": [0.5, 0.5], "weights": [0.75]}]},
    {"kind": "bezier", "degree": 2, "faces": [{"face": [0, 1], "points": [0.9999847412109375, 1.52587890625e-5]}]},
    {"kind": "bezier", "degree": 2, "faces": [{"face": [0, 3], "points": [1, -0.0]}]},
    {"kind": "bezier", "degree": 2, "faces": [{"face": [2, 3], "points": [0.5, 0.5]}, {"face": [0, 1], "points": [0.5, 0.5]}]},
    {"kind": "monotonic", "degree": 2, "vertexMaps": [{"vertex": 1, "coefficients": [0, 0.5, 1]}]}
  ]
}"#
            .into(),
        },
        WriterVector {
            name: "appendix-a",
            // The model of spec Appendix A: its binary output is the dump printed there.
            input: r#"{"version":"1.0","dimension":2,"metadata":{"name":"t"},"vertices":[0,0,1,0,0,1],"simplices":[0,1,2],"values":[-1,1,1],"stages":[{"kind":"bezier","degree":2,"faces":[{"face":[1,2],"points":[0.5,0.5]}]}]}"#
                .into(),
        },
    ]
}

/// The bytes a writer produces for `vector` in one output form.
///
/// # Errors
/// A message when the input does not read or the model does not write.
pub fn writer_output(
    vector: &WriterVector,
    encoding: Encoding,
    pretty: bool,
) -> Result<Vec<u8>, String> {
    let doc = io::from_slice(vector.input.as_bytes())
        .map_err(|e| format!("{}.input.json: {e}", vector.name))?;
    io::to_vec(
        &doc.model,
        encoding,
        WriteOptions {
            pretty,
            json_in_container: false,
        },
    )
    .map_err(|e| format!("{}: {e}", vector.name))
}

/// Writes every writer vector (input and outputs) into `dir`; returns the paths written.
///
/// # Errors
/// I/O errors, or a vector whose input does not read.
pub fn write_writer_vectors(dir: &Path) -> Result<Vec<PathBuf>, String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut written = Vec::new();
    for vector in writer_vectors() {
        let mut files = vec![(
            dir.join(format!("{}.input.json", vector.name)),
            vector.input.clone().into_bytes(),
        )];
        for (suffix, encoding, pretty) in OUTPUTS {
            files.push((
                dir.join(format!("{}.{suffix}", vector.name)),
                writer_output(&vector, encoding, pretty)?,
            ));
        }
        for (path, bytes) in files {
            io::write_atomic(&path, |w| std::io::Write::write_all(w, &bytes))
                .map_err(|e| format!("{}: {e}", path.display()))?;
            written.push(path);
        }
    }
    Ok(written)
}
