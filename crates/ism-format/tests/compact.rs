//! The compact binary encoding (spec §7.4.1): its bytes written out by hand from the spec, bincode's
//! own varint encoder as a second writer, and the errors of its varints (non-minimal, truncated,
//! bad first byte, a length the payload cannot hold), each typed and located.

use ism_format::builder::StageBuilder;
use ism_format::io::{self, WriteOptions, HEADER_LEN};
use ism_format::{Encoding, Model, Rule};

mod common;
use common::appendix_a;

fn f64s(xs: &[f64]) -> Vec<u8> {
    xs.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Appendix A's payload in the compact encoding, written field by field from spec §7.4/§7.4.1.
fn appendix_a_payload() -> Vec<u8> {
    let mut p = Vec::new();
    p.extend([3, b'1', b'.', b'0']); // version
    p.push(2); // dimension
    p.extend([1, 1, b't', 0, 0, 0]); // metadata: name "t", three absent
    p.push(6); // vertices
    p.extend(f64s(&[0.0, 0.0, 1.0, 0.0, 0.0, 1.0]));
    p.extend([3, 0, 1, 2]); // simplices
    p.push(3); // values
    p.extend(f64s(&[-1.0, 1.0, 1.0]));
    p.extend(f64s(&[0.0])); // level
    p.push(1); // stages
    p.extend([0, 2, 0, 0]); // kind bezier, degree 2, direction implicit, no name
    p.push(1); // faces
    p.extend([2, 1, 2]); // face [1, 2]
    p.push(2); // points
    p.extend(f64s(&[0.5, 0.5]));
    p.push(0); // weights
    p.push(0); // vertexMaps
    p.extend([4, b'n', b'u', b'l', b'l']); // stage extras
    p.extend([0, 0, 0]); // extensionsUsed, extensionsRequired, extensions
    p.extend([4, b'n', b'u', b'l', b'l']); // extras
    p
}

#[test]
fn appendix_a_in_the_compact_encoding_is_the_bytes_of_the_spec() {
    let payload = appendix_a_payload();
    assert_eq!(payload.len(), 138);
    let written = io::to_vec(&appendix_a(), Encoding::Compact, WriteOptions::default()).unwrap();
    assert_eq!(written[12], 4, "encoding tag");
    assert_eq!(&written[HEADER_LEN..], &payload[..]);
    let doc = io::from_slice(&written).unwrap();
    assert_eq!(doc.encoding, Encoding::Compact);
    assert_eq!(doc.model, appendix_a());
}

/// A compact file of Appendix A whose payload has `at..at + cut` replaced by `with`.
fn patched(at: usize, cut: usize, with: &[u8]) -> Vec<u8> {
    let mut payload = appendix_a_payload();
    payload.splice(at..at + cut, with.iter().copied());
    let mut file = io::header(Encoding::Compact, ism_format::FORMAT_VERSION, &payload).to_vec();
    file.extend(payload);
    file
}

/// Payload offsets of Appendix A's compact payload.
const VERTICES_LEN: usize = 11;
const SIMPLICES: usize = VERTICES_LEN + 1 + 48;
const KIND: usize = SIMPLICES + 4 + 1 + 24 + 8 + 1;
const FACE_LEN: usize = KIND + 5;

fn error_at(file: &[u8]) -> (Rule, Option<String>, Option<u64>) {
    let located = |e: ism_format::Error| {
        let d = e.diagnostics()[0].clone();
        (e.rule().unwrap(), d.location.pointer, d.location.offset)
    };
    let in_memory = located(io::from_slice(file).expect_err("malformed compact file read"));
    let streamed = located(
        io::read_with(file, &io::ReadOptions::default()).expect_err("malformed file streamed"),
    );
    assert_eq!(in_memory, streamed, "streamed and in-memory reads disagree");
    in_memory
}

fn at(payload_offset: usize) -> Option<u64> {
    Some((HEADER_LEN + payload_offset) as u64)
}

#[test]
fn varint_errors_are_typed_and_located_at_their_first_byte() {
    let m = Rule::Malformed;
    // A non-minimal length: 6 written as `FB 06 00`.
    let f = patched(VERTICES_LEN, 1, &[0xFB, 6, 0]);
    assert_eq!(
        error_at(&f),
        (m, Some("/vertices".into()), at(VERTICES_LEN))
    );
    // A non-minimal id: 1 written as `FC 01 00 00 00`, inside a face record.
    let f = patched(FACE_LEN + 1, 1, &[0xFC, 1, 0, 0, 0]);
    assert_eq!(
        error_at(&f),
        (m, Some("/stages/0/faces/0/face".into()), at(FACE_LEN + 1))
    );
    // A non-minimal u64 form of a length below 2³².
    let f = patched(VERTICES_LEN, 1, &[0xFD, 6, 0, 0, 0, 0, 0, 0, 0]);
    assert_eq!(
        error_at(&f),
        (m, Some("/vertices".into()), at(VERTICES_LEN))
    );
    // First bytes 254 and 255 are never a varint; 253 is none of a u32 member.
    for first in [0xFE, 0xFF] {
        let f = patched(VERTICES_LEN, 1, &[first]);
        assert_eq!(
            error_at(&f),
            (m, Some("/vertices".into()), at(VERTICES_LEN))
        );
    }
    let f = patched(KIND, 1, &[0xFD, 0, 0, 0, 0, 1, 0, 0, 0]);
    assert_eq!(error_at(&f), (m, Some("/stages/0/kind".into()), at(KIND)));
    // A simplex id of 2³²: out of a u32's range whatever its form.
    let f = patched(SIMPLICES + 1, 1, &[0xFD, 0, 0, 0, 0, 1, 0, 0, 0]);
    assert_eq!(
        error_at(&f),
        (m, Some("/simplices".into()), at(SIMPLICES + 1))
    );
    // A length of 2⁶¹ (minimal, u64 form): more than the payload holds, refused before allocating.
    let mut huge = vec![0xFD];
    huge.extend((1u64 << 61).to_le_bytes());
    let f = patched(VERTICES_LEN, 1, &huge);
    assert_eq!(
        error_at(&f),
        (m, Some("/vertices".into()), at(VERTICES_LEN))
    );
    // A varint cut by the payload's end: at its first byte.
    let mut payload = appendix_a_payload();
    payload.truncate(VERTICES_LEN);
    payload.extend([0xFC, 6, 0]);
    let mut file = io::header(Encoding::Compact, ism_format::FORMAT_VERSION, &payload).to_vec();
    file.extend(&payload);
    assert_eq!(
        error_at(&file),
        (m, Some("/vertices".into()), at(VERTICES_LEN))
    );
}

#[test]
fn varints_agree_with_bincodes_own_encoder() {
    // The boundaries of every varint form, as a simplex id (u32) and as a vertex count's length
    // (u64 is only reachable as a length, so bincode's u32 encoder is the peer here).
    for id in [
        0u32,
        250,
        251,
        252,
        255,
        256,
        65535,
        65536,
        1 << 24,
        u32::MAX - 1,
        u32::MAX,
    ] {
        let bincode_bytes = bincode::encode_to_vec(id, io::compact_config()).unwrap();
        let mut m = appendix_a();
        // Three new vertices so that the id and its two neighbours are simplex ids of a model
        // that decodes (the structural check is off below: only the bytes matter here).
        m.simplices = vec![id, id, id];
        let bytes = io::to_vec(&m, Encoding::Compact, WriteOptions::default()).unwrap();
        let p = &bytes[HEADER_LEN + SIMPLICES..];
        assert_eq!(p[0], 3);
        let n = bincode_bytes.len();
        for k in 0..3 {
            assert_eq!(
                &p[1 + k * n..1 + (k + 1) * n],
                &bincode_bytes[..],
                "id {id}"
            );
        }
        let options = io::ReadOptions {
            check_structure: false,
            ..io::ReadOptions::default()
        };
        let back = io::from_slice_with(&bytes, &options).unwrap();
        assert_eq!(back.model.simplices, vec![id, id, id]);
    }
}

/// Many records and ids above 250 (three-byte varints) so that the record-at-hand fast path and a
/// streamed window boundary are both crossed; every encoding reads back the same model.
#[test]
fn large_models_read_back_alike_in_memory_and_streamed() {
    let n = 40_000u32;
    let mut m = Model::new(2);
    m.vertices = (0..n)
        .flat_map(|i| [f64::from(i), f64::from(i % 7)])
        .collect();
    m.values = vec![1.0; n as usize];
    m.simplices = (0..n - 2).flat_map(|i| [i, i + 1, i + 2]).collect();
    let mut stage = StageBuilder::bezier(2);
    for i in 0..n - 1 {
        stage = stage.face(&[i, i + 1], &[0.25 * f64::from(i), 0.5], &[]);
    }
    m.stages.push(stage.build());
    let options = io::ReadOptions {
        check_structure: false,
        ..io::ReadOptions::default()
    };
    let compact = io::to_vec(&m, Encoding::Compact, WriteOptions::default()).unwrap();
    let binary = io::to_vec(&m, Encoding::Binary, WriteOptions::default()).unwrap();
    assert!(compact.len() < binary.len());
    for bytes in [&compact, &binary] {
        let a = io::from_slice_with(bytes, &options).unwrap().model;
        let b = io::read_with(&bytes[..], &options).unwrap().model;
        assert_eq!(a, m);
        assert_eq!(b, m);
    }
}
