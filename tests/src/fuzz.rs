//! The properties the fuzz targets of `fuzz/` check beyond the model readers, in one place: the
//! targets call these on the fuzzer's bytes, and `tests/fuzz_corpora.rs` replays every kept input
//! (`fuzz/corpus/<target>/`) and every fixed crash (`fuzz/artifacts/<target>/`) through the same
//! functions, so a corpus is a regression test.
//!
//! Each function panics exactly when the property fails; bad input must give a typed error.

use std::path::Path;

use ism_export::import::{read_mesh, to_model, ImportFormat, ImportOptions};
use ism_format::io::{self, ReadOptions, WriteOptions};
use ism_format::{Encoding, IndexedModel, Model};

pub mod generated;

/// A model as a writer writes it back: its own format version (spec §8.1).
fn as_written(model: &Model) -> Model {
    Model {
        version: ism_format::FORMAT_VERSION.to_string(),
        ..model.clone()
    }
}

/// What `ism` writes, `ism` reads: `model` encodes in every encoding, and each file reads back
/// (with the reader's structural checks) to the same model. `what` names the producer.
fn written_model_reads_back(model: &Model, what: &str) {
    for encoding in Encoding::ALL {
        let bytes = io::to_vec(model, encoding, WriteOptions::default())
            .unwrap_or_else(|e| panic!("{what} made a model the {encoding:?} writer refuses: {e}"));
        let doc = io::from_slice(&bytes)
            .unwrap_or_else(|e| panic!("{what} made a model the reader refuses: {e}"));
        assert_eq!(
            doc.model,
            as_written(model),
            "{what}: {encoding:?} changed it"
        );
    }
}

/// Targets `read_any`, `read_binary`, `read_msgpack`, `read_json` (beside their round trip): the
/// model readers issue 13 added agree with the in-memory checked read on the same bytes — the same
/// model, or an error with the same text (rule, location and message):
/// - the streamed read ([`io::read_with`]: a binary payload decoded through its window as it
///   arrives, checksummed on the way);
/// - a read keeping no record numbers ([`io::read_path_with`] with
///   [`ReadOptions::keep_record_numbers`] off, from a file: `ism info`'s read), which keeps the
///   same face ids;
/// - the indexed read ([`io::from_slice_indexed`]: the check that builds the face tables instead
///   of scanning the records), and the lazy index ([`IndexedModel::new_lazy_or_model`], the
///   validator's and the exporter's), whose records found by face ids
///   ([`IndexedModel::simplex_records`]) and tables once built are the eager index's.
pub fn readers_agree(bytes: &[u8]) {
    let checked = ReadOptions::default();
    let slice = io::from_slice_with(bytes, &checked);
    let text = |r: &ism_format::Result<io::Document>| match r {
        Ok(d) => Ok(d.model.clone()),
        Err(e) => Err(e.to_string()),
    };
    let stream = io::read_with(std::io::Cursor::new(bytes), &checked);
    assert_eq!(text(&stream), text(&slice), "streamed read");

    let file = tempfile::NamedTempFile::new().expect("temporary file");
    std::fs::write(file.path(), bytes).expect("write the temporary file");
    let lean = ReadOptions {
        keep_record_numbers: false,
        ..checked
    };
    match (io::read_path_with(file.path(), &lean), &slice) {
        (Ok(lean), Ok(full)) => {
            let (a, b) = (&lean.model, &full.model);
            assert_eq!(
                (&a.vertices, &a.simplices, &a.values),
                (&b.vertices, &b.simplices, &b.values),
                "lean read"
            );
            assert_eq!(a.stages.len(), b.stages.len(), "lean read");
            for (a, b) in a.stages.iter().zip(&b.stages) {
                assert_eq!(a.faces.all_face_ids(), b.faces.all_face_ids(), "lean read");
                let lengths = |t: &ism_format::FaceTable| {
                    (0..t.len()).map(|r| t.lengths(r)).collect::<Vec<_>>()
                };
                assert_eq!(lengths(&a.faces), lengths(&b.faces), "lean read");
            }
        }
        (Err(a), Err(b)) => assert_eq!(a.to_string(), b.to_string(), "lean read"),
        (a, b) => panic!(
            "lean read {:?}, full read {:?}",
            a.map(|_| ()),
            b.as_ref().map(|_| ())
        ),
    }

    let indexed = io::from_slice_indexed(bytes, &checked);
    match (&indexed, &slice) {
        (Ok(i), Ok(d)) => {
            assert_eq!(i.model.model(), &d.model, "indexed read");
            match IndexedModel::new_lazy_or_model(d.model.clone()) {
                Ok(lazy) => {
                    assert_eq!(lazy.diagnostics(), i.model.diagnostics(), "lazy index");
                    // Before its tables are built, the lazy index finds each simplex's face
                    // records by their ids (an export's route): the eager index's records.
                    for (k, stage) in d.model.stages.iter().enumerate() {
                        if stage.kind == ism_format::StageKind::Monotonic {
                            continue;
                        }
                        for s in 0..d.model.num_simplices() {
                            assert_eq!(
                                lazy.simplex_records(k, s),
                                i.model.simplex_records(k, s),
                                "lazy index: records of stage {k} on simplex {s}"
                            );
                        }
                    }
                    assert_eq!(lazy.topology(), i.model.topology(), "lazy index");
                }
                Err((_, e)) => panic!("the lazy index refuses a checked model: {e}"),
            }
        }
        (Err(a), Err(b)) => assert_eq!(a.to_string(), b.to_string(), "indexed read"),
        (a, b) => panic!(
            "indexed read {:?}, checked read {:?}",
            a.as_ref().map(|_| ()),
            b.as_ref().map(|_| ())
        ),
    }
}

/// [`readers_agree`] on a payload behind a valid container of `encoding` (the payload targets).
pub fn readers_agree_on_payload(encoding: Encoding, payload: &[u8]) {
    let mut bytes = io::header(encoding, ism_format::FORMAT_VERSION, payload).to_vec();
    bytes.extend_from_slice(payload);
    readers_agree(&bytes);
}

/// Target `read_compressed` (spec §7.4.2). The first byte picks what the rest is:
/// - even: a compressed payload as it is, behind a valid container (the length, the xz framing,
///   bombs, bytes after the stream): the readers agree ([`readers_agree`]) and never panic;
/// - odd: a compact payload, compressed here (xz preset 0): the compressed file reads exactly as
///   the `.ismc` file of the same payload does — the same model, or the same error (rule, location
///   and message): the compact reader is the peer that says what the streamed decompression must
///   give. A model that reads is written compressed and reads back to itself.
pub fn read_compressed(data: &[u8]) {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    if mode % 2 == 0 {
        readers_agree_on_payload(Encoding::Compressed, rest);
        return;
    }
    let contain = |encoding: Encoding, payload: &[u8]| {
        let mut bytes = io::header(encoding, ism_format::FORMAT_VERSION, payload).to_vec();
        bytes.extend_from_slice(payload);
        bytes
    };
    let mut xz = liblzma::write::XzEncoder::new((rest.len() as u64).to_le_bytes().to_vec(), 0);
    std::io::Write::write_all(&mut xz, rest).expect("in memory");
    let compressed = contain(Encoding::Compressed, &xz.finish().expect("in memory"));
    readers_agree(&compressed);
    let text = |r: ism_format::Result<io::Document>| match r {
        Ok(d) => Ok(d.model),
        Err(e) => Err(e.to_string()),
    };
    let got = text(io::from_slice(&compressed));
    assert_eq!(
        got,
        text(io::from_slice(&contain(Encoding::Compact, rest))),
        "the compressed read differs from the compact read of the same payload"
    );
    if let Ok(model) = got {
        let again = io::to_vec(&model, Encoding::Compressed, WriteOptions::default())
            .expect("a model read is written");
        assert_eq!(io::from_slice(&again).expect("re-read").model, model);
    }
}

/// Target `read_structured` (spec §7.4.3): a structured payload behind a valid container. The
/// readers agree ([`readers_agree`]); a model that reads is written back structured and reads to
/// itself, and the writer's bytes are canonical (written again from what they read, the same
/// bytes). A payload that reads need not be the writer's own: readers accept `recordForm` 0 where
/// the writer would choose 1, and any lattice width that holds the points.
pub fn read_structured(payload: &[u8]) {
    readers_agree_on_payload(Encoding::Structured, payload);
    let mut bytes = io::header(Encoding::Structured, ism_format::FORMAT_VERSION, payload).to_vec();
    bytes.extend_from_slice(payload);
    let unchecked = ReadOptions {
        check_structure: false,
        ..ReadOptions::default()
    };
    let Ok(doc) = io::from_slice_with(&bytes, &unchecked) else {
        return;
    };
    let Ok(again) = io::to_vec(&doc.model, Encoding::Structured, WriteOptions::default()) else {
        // Only a number no writer writes (NaN, infinity) stops the writer.
        assert!(io::check_writable(&doc.model).is_err());
        return;
    };
    let back = io::from_slice_with(&again, &unchecked)
        .expect("a written structured file reads")
        .model;
    let binary = |m: &Model| io::encode_payload(m, Encoding::Binary, false).expect("binary");
    assert_eq!(
        binary(&back),
        binary(&as_written(&doc.model)),
        "structured round trip"
    );
    assert_eq!(
        io::to_vec(&back, Encoding::Structured, WriteOptions::default()).expect("re-encode"),
        again,
        "the structured writer is not canonical"
    );
}

/// Target `import_mesh`: the bytes as `.vtu`, legacy `.vtk` and `.msh` (`ism import`'s parsers).
/// Each parse gives a mesh or a typed error; a mesh converts to a model or a typed error (with the
/// first field and with a named one at another level); a converted model is one `ism` reads back.
pub fn import_mesh(data: &[u8]) {
    for format in [
        ImportFormat::Vtu,
        ImportFormat::VtkLegacy,
        ImportFormat::Msh,
    ] {
        let Ok(raw) = read_mesh(data, format) else {
            continue;
        };
        let mut options = vec![ImportOptions::default()];
        if let Some((name, values)) = raw.fields.last() {
            // A level inside the field's range: the other common use.
            let level = values
                .iter()
                .copied()
                .find(|v| v.is_finite())
                .unwrap_or(0.5)
                + 0.5;
            options.push(ImportOptions {
                field: Some(name.clone()),
                level,
                ..ImportOptions::default()
            });
        }
        for o in &options {
            if let Ok((model, _)) = to_model(&raw, o) {
                written_model_reads_back(&model, &format!("import of {format:?}"));
            }
        }
    }
}

/// Target `fit_mesh`: the bytes as OBJ and as glTF/GLB (`ism fit --mesh`'s readers: `ism_export`'s
/// `obj::read_obj` and `gltf::read_gltf`, then `ism_fit`'s welding). Never a panic; a mesh read has triangles whose ids are in range and finite positions.
pub fn fit_mesh(data: &[u8]) {
    use ism_fit::mesh::TriangleMesh;
    // A path whose directory holds no buffer: relative glTF buffer URIs fail as missing files.
    let path = Path::new("/nonexistent-ism-fuzz/mesh.gltf");
    for mesh in [
        TriangleMesh::from_obj(data, path),
        TriangleMesh::from_gltf(data, path),
    ]
    .into_iter()
    .flatten()
    {
        assert!(!mesh.triangles.is_empty());
        for t in &mesh.triangles {
            assert!(t.iter().all(|&v| (v as usize) < mesh.positions.len()));
        }
        assert!(mesh.positions.iter().flatten().all(|x| x.is_finite()));
    }
}

/// Most simplices and handles of a Hermite input that the `read_hermite` target also fits (the fit
/// is polynomial in the model's size; the fuzzer's inputs are meant to stay fast).
const HERMITE_FIT_MAX_SIMPLICES: usize = 48;
const HERMITE_FIT_MAX_HANDLES: usize = 12;

/// Target `read_hermite`: the bytes as an `ism fit --hermite` handles file with its complex inline.
/// Parsing and building the base model give a value or a typed error; a small base model is fitted
/// (with at most two sweeps), which gives a typed error or a model `ism` reads back.
pub fn read_hermite(data: &[u8]) {
    use ism_fit::hermite::{fit_hermite, HermiteData};
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(parsed) = HermiteData::from_json(text) else {
        return;
    };
    if parsed.model.is_some() {
        // A model path names a file; the model readers have their own targets.
        return;
    }
    let Ok(model) = parsed.base_model(None) else {
        return;
    };
    written_model_reads_back(&model, "the Hermite base model");
    if model.num_simplices() > HERMITE_FIT_MAX_SIMPLICES
        || parsed.handles.len() > HERMITE_FIT_MAX_HANDLES
    {
        return;
    }
    let mut options = parsed.options();
    options.iterations = options.iterations.min(2);
    if let Ok(fit) = fit_hermite(&model, &parsed.handles, &options) {
        written_model_reads_back(&fit.model, "the Hermite fit");
    }
}

/// Target `validate_generated`: the validator on a structurally valid model built from the bytes
/// ([`generated::Generated`]), with and without its theorems. It never panics, and whenever it
/// says VALID, no stage has `det DY ≤ 0` at any sampled dyadic point of any simplex, decided exactly
/// by [`generated`]'s own evaluation.
pub fn validate_generated(data: &[u8]) {
    use ism_validate::{validate, Options, Verdict};
    let Some(g) = generated::Generated::from_bytes(data) else {
        return;
    };
    let structural = ism_format::structure::check(&g.model, 1);
    if structural
        .iter()
        .any(|d| d.severity == ism_format::Severity::Error)
    {
        // A perturbation made a simplex degenerate: not a model the validator certifies.
        return;
    }
    for theorems in [true, false] {
        let options = Options {
            threads: 1,
            // A smaller budget than the CLI's keeps each input fast; VALID must be right at any.
            max_pieces: 1024,
            theorems,
            ..Options::default()
        };
        let report = validate(&g.model, &options);
        if report.verdict == Verdict::Valid {
            let bad = g.nonpositive_jacobians(3);
            assert!(
                bad.is_empty(),
                "validator (theorems {theorems}) says VALID, but det DY <= 0 at (stage, simplex, point) {bad:?} of {:?}",
                g.model
            );
        }
    }
}
