//! The structured encoding (spec §7.4.3): Appendix A's payload written out byte by byte from the
//! spec, the canonical writer's choices (record form, dims, lattice width) checked against bytes
//! assembled by hand, every reader error of the `Records` section typed and located, and round
//! trips of the spec's examples and of generated models.

use ism_format::builder::StageBuilder;
use ism_format::io::{self, ReadOptions, WriteOptions, HEADER_LEN};
use ism_format::refine::KuhnRefinement;
use ism_format::{Encoding, FaceRecord, FaceTable, Model, Rule, Stage, StageKind, VertexMap};
use proptest::prelude::*;

mod common;
use common::appendix_a;

fn f64s(xs: &[f64]) -> Vec<u8> {
    xs.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Appendix A's payload up to its stage's `Records` section, in the structured encoding.
fn head() -> Vec<u8> {
    let mut p = Vec::new();
    p.extend([3, b'1', b'.', b'0']); // version "1.0"
    p.push(2); // dimension
    p.extend([1, 1, b't', 0, 0, 0]); // metadata: name "t", generator/units/description absent
    p.push(0); // complexForm 0
    p.push(6); // vertices: 6
    p.extend(f64s(&[0.0, 0.0, 1.0, 0.0, 0.0, 1.0]));
    p.extend([3, 0, 1, 2]); // simplices: 3 ids, the triangle 0 1 2
    p.push(3); // values: 3
    p.extend(f64s(&[-1.0, 1.0, 1.0]));
    p.extend(f64s(&[0.0])); // level
    p.push(1); // stages: 1
    p.extend([0, 2, 0, 0]); // kind bezier, degree 2, direction implicit, name absent
    p
}

/// What follows the `Records` section: the stage's vertexMaps and extras, the model's tail.
fn tail() -> Vec<u8> {
    let mut p = Vec::new();
    p.push(0); // vertexMaps: 0
    p.extend([4, b'n', b'u', b'l', b'l']); // stage extras "null"
    p.extend([0, 0, 0]); // extensionsUsed, extensionsRequired, extensions
    p.extend([4, b'n', b'u', b'l', b'l']); // extras "null"
    p
}

/// Appendix A's `Records` section. The complex's 1-faces (edges) are, sorted, [0,1] [0,2] [1,2]:
/// the record on [1,2] is bit 2 of a one-byte mask. Its one point (0.5, 0.5) is on the 2^-8
/// lattice: n1 = 0.5 · 256 = 128, and c0 = (256 − 128) / 256 = 0.5.
const APPENDIX_A_RECORDS: [u8; 5] = [
    1,     // recordForm 1: by the complex
    0b10,  // dims: records of 1-faces only
    0b100, // mask_1: edge 2 of [0,1] [0,2] [1,2]
    1,     // width 1
    128,   // the point's n1
];

/// Payload offsets in Appendix A's structured payload.
const COMPLEX_FORM: usize = 11;
const RECORDS: usize = 11 + 1 + 1 + 48 + 4 + 1 + 24 + 8 + 1 + 4;

fn payload_with(records: &[u8]) -> Vec<u8> {
    let mut p = head();
    p.extend(records);
    p.extend(tail());
    p
}

fn file_of(payload: &[u8]) -> Vec<u8> {
    let mut file = io::header(Encoding::Structured, ism_format::FORMAT_VERSION, payload).to_vec();
    file.extend(payload);
    file
}

fn at(payload_offset: usize) -> Option<u64> {
    Some((HEADER_LEN + payload_offset) as u64)
}

fn unchecked() -> ReadOptions {
    ReadOptions {
        check_structure: false,
        ..ReadOptions::default()
    }
}

fn error_of(payload: &[u8]) -> (Rule, Option<String>, Option<u64>) {
    let e = io::from_slice_with(&file_of(payload), &unchecked()).expect_err("malformed file read");
    let d = e.diagnostics()[0].clone();
    (e.rule().unwrap(), d.location.pointer, d.location.offset)
}

/// The `Records` section the writer gives a stage of Appendix A's complex.
fn written_records(stage: Stage) -> Vec<u8> {
    let mut m = appendix_a();
    m.stages = vec![stage];
    let payload = io::encode_payload(&m, Encoding::Structured, false).unwrap();
    // The head is the same up to the stage's name; the tail after the records is fixed length
    // unless the stage has vertex maps (none here).
    let h = head();
    let h = &h[..h.len() - 4];
    assert_eq!(&payload[..h.len()], h);
    let rest = &payload[h.len() + 4..];
    assert!(rest.ends_with(&tail()));
    let read = io::from_slice_with(
        &io::to_vec(&m, Encoding::Structured, WriteOptions::default()).unwrap(),
        &unchecked(),
    )
    .unwrap()
    .model;
    assert_eq!(
        io::encode_payload(&read, Encoding::Binary, false).unwrap(),
        io::encode_payload(&m, Encoding::Binary, false).unwrap()
    );
    rest[..rest.len() - tail().len()].to_vec()
}

#[test]
fn appendix_a_in_the_structured_encoding_is_the_bytes_of_the_spec() {
    let payload = payload_with(&APPENDIX_A_RECORDS);
    // The compact payload (138 bytes) without its record (22 bytes: count, face, points, weights),
    // with complexForm and the 5 bytes of the section.
    assert_eq!(payload.len(), 138 - 22 + 1 + 5);
    let written = io::to_vec(&appendix_a(), Encoding::Structured, WriteOptions::default()).unwrap();
    assert_eq!(written[12], 6, "encoding tag");
    assert_eq!(&written[HEADER_LEN..], &payload[..]);
    let doc = io::from_slice(&written).unwrap();
    assert_eq!(doc.encoding, Encoding::Structured);
    assert_eq!(doc.model, appendix_a());
    assert_eq!(
        Encoding::from_path(std::path::Path::new("a.isms")),
        Some(Encoding::Structured)
    );
    assert_eq!("structured".parse::<Encoding>(), Ok(Encoding::Structured));
}

#[test]
fn records_listed_as_in_the_compact_encoding_read_alike() {
    // recordForm 0, then `faces` exactly as §7.4.1 writes them.
    let mut records = vec![0, 1, 2, 1, 2, 2];
    records.extend(f64s(&[0.5, 0.5]));
    records.push(0); // weights
    let doc = io::from_slice(&file_of(&payload_with(&records))).unwrap();
    assert_eq!(doc.model, appendix_a());
}

fn bezier(face: &[u32], points: &[f64]) -> Stage {
    StageBuilder::bezier(2).face(face, points, &[]).build()
}

#[test]
fn the_writer_picks_the_smallest_lattice_width() {
    // A −0.0 coordinate is on no lattice: its integer 0 would read back as +0.0.
    let mut expected = vec![1, 0b10, 0b100, 0];
    expected.extend(f64s(&[1.0, -0.0]));
    assert_eq!(written_records(bezier(&[1, 2], &[1.0, -0.0])), expected);
    // +0.0 is: n1 = 0, c0 = 256/256.
    assert_eq!(
        written_records(bezier(&[1, 2], &[1.0, 0.0])),
        [1, 0b10, 0b100, 1, 0]
    );
    // 2^-16 needs two bytes: n1 = 1 at w = 2, little-endian.
    let tiny = 1.0 / 65536.0;
    assert_eq!(
        written_records(bezier(&[1, 2], &[1.0 - tiny, tiny])),
        [1, 0b10, 0b100, 2, 1, 0]
    );
    // 2^-32 needs four: n1 = 1 at w = 4.
    let tinier = 1.0 / 4294967296.0;
    assert_eq!(
        written_records(bezier(&[1, 2], &[1.0 - tinier, tinier])),
        [1, 0b10, 0b100, 4, 1, 0, 0, 0]
    );
    // 2^-40 needs more than four: f64.
    let off = f64::powi(2.0, -40);
    let mut expected = vec![1, 0b10, 0b100, 0];
    expected.extend(f64s(&[1.0 - off, off]));
    assert_eq!(
        written_records(bezier(&[1, 2], &[1.0 - off, off])),
        expected
    );
    // A point whose coordinates do not sum to 1 is not as the lattice stores it.
    let mut expected = vec![1, 0b10, 0b100, 0];
    expected.extend(f64s(&[0.25, 0.5]));
    assert_eq!(written_records(bezier(&[1, 2], &[0.25, 0.5])), expected);
    // A negative c0 is carried: on a triangle (degree 3, one point) n1 = n2 = 192 sum to 384 > 256,
    // c0 = (256 − 384) / 256 = −0.5.
    let s = StageBuilder::bezier(3)
        .face(&[0, 1, 2], &[-0.5, 0.75, 0.75], &[])
        .build();
    assert_eq!(written_records(s), [1, 0b100, 0b1, 1, 192, 192]);
    // A coordinate of 1 is not below 2^(8w) · 2^(-8w): no lattice holds (0, 1).
    let mut expected = vec![1, 0b10, 0b100, 0];
    expected.extend(f64s(&[0.0, 1.0]));
    assert_eq!(written_records(bezier(&[1, 2], &[0.0, 1.0])), expected);
}

#[test]
fn the_writer_lists_records_the_masks_cannot_give() {
    // Out of mask order: [1,2] (edge 2) before [0,1] (edge 0).
    let s = StageBuilder::bezier(2)
        .face(&[1, 2], &[0.5, 0.5], &[])
        .face(&[0, 1], &[0.5, 0.5], &[])
        .build();
    let records = written_records(s);
    assert_eq!(&records[..2], [0, 2], "recordForm 0, two records");
    // A record on a face the complex does not have.
    let records = written_records(bezier(&[0, 3], &[0.5, 0.5]));
    assert_eq!(&records[..5], [0, 1, 2, 0, 3]);
    // The wrong number of points (two points on an edge of a degree-2 stage, which owns one).
    let records = written_records(bezier(&[1, 2], &[0.5, 0.5, 0.5, 0.5]));
    assert_eq!(&records[..5], [0, 1, 2, 1, 2]);
    // Weights in a Bézier stage.
    let s = StageBuilder::bezier(2)
        .face(&[1, 2], &[0.5, 0.5], &[2.0])
        .build();
    assert_eq!(&written_records(s)[..5], [0, 1, 2, 1, 2]);
    // Unsorted ids: [2,1] is not the face [1,2]. (The builder would sort them.)
    let mut s = bezier(&[1, 2], &[0.5, 0.5]);
    s.faces = FaceTable::from(vec![FaceRecord {
        face: vec![2, 1],
        points: vec![0.5, 0.5],
        weights: vec![],
    }]);
    assert_eq!(&written_records(s)[..5], [0, 1, 2, 2, 1]);
    // The same face twice.
    let s = StageBuilder::bezier(2)
        .face(&[1, 2], &[0.5, 0.5], &[])
        .face(&[1, 2], &[0.5, 0.5], &[])
        .build();
    assert_eq!(&written_records(s)[..2], [0, 2]);
}

#[test]
fn the_writer_gives_records_by_the_complex_whenever_it_can() {
    // A monotonic stage: no records, dims 0, and width 1 (every point of none is on the lattice).
    let s = StageBuilder::monotonic(2).build();
    assert_eq!(written_records(s), [1, 0, 1]);
    // A rational stage with a vertex record and an edge record: dims 0b11; the vertex (k = 0)
    // point takes no bytes; the weights follow the points, in record order.
    let s = Stage {
        kind: StageKind::Rational,
        degree: 2,
        direction: Default::default(),
        name: None,
        faces: FaceTable::from(vec![
            FaceRecord {
                face: vec![1],
                points: vec![1.0],
                weights: vec![3.0],
            },
            FaceRecord {
                face: vec![0, 2],
                points: vec![0.25, 0.75],
                weights: vec![2.0],
            },
        ]),
        vertex_maps: vec![],
        extras: Default::default(),
    };
    let mut expected = vec![1, 0b11, 0b010, 0b010, 1, 192];
    expected.extend(f64s(&[3.0, 2.0]));
    assert_eq!(written_records(s), expected);
    // A triangle record at degree 3 (one owned point, three coordinates: two integers).
    let s = StageBuilder::bezier(3)
        .face(&[0, 1, 2], &[0.5, 0.25, 0.25], &[])
        .build();
    assert_eq!(written_records(s), [1, 0b100, 0b1, 1, 64, 64]);
    // Degree 1: an edge record owns no point, and still has its bit.
    let s = StageBuilder::bezier(1).face(&[0, 1], &[], &[]).build();
    assert_eq!(written_records(s), [1, 0b10, 0b1, 1]);
}

#[test]
fn vertex_records_read_as_the_point_1() {
    // dims 0b1: the 0-faces [0] [1] [2], all three set; width 1: no bytes per point.
    let m = io::from_slice_with(&file_of(&payload_with(&[1, 0b1, 0b111, 1])), &unchecked())
        .unwrap()
        .model;
    let records = m.stages[0].faces.to_records();
    assert_eq!(records.len(), 3);
    for (v, r) in records.iter().enumerate() {
        assert_eq!(r.face, [v as u32]);
        assert_eq!(r.points, [1.0]);
        assert!(r.weights.is_empty());
    }
}

#[test]
fn faces_come_from_the_simplices_as_decoded() {
    // Simplices [5 5 3] and [3 5 9]: repeated ids count once, ids out of range are ids; the
    // 1-faces are [3,5] [3,9] [5,9]. The mask picks [3,9] (bit 1).
    let mut p = Vec::new();
    p.extend([3, b'1', b'.', b'0', 2, 0, 0, 0, 0]); // version, dimension, no metadata
    p.push(0); // complexForm
    p.push(0); // vertices: none
    p.extend([6, 5, 5, 3, 3, 5, 9]); // simplices
    p.push(0); // values: none
    p.extend(f64s(&[0.0])); // level
    p.extend([1, 0, 2, 0, 0]); // one stage: bezier, degree 2, implicit, no name
    p.extend([1, 0b10, 0b010, 1, 64]); // records: [3,9] with (0.75, 0.25)
    p.extend(tail());
    let m = io::from_slice_with(&file_of(&p), &unchecked())
        .unwrap()
        .model;
    let records = m.stages[0].faces.to_records();
    assert_eq!(records.len(), 1);
    assert_eq!(records[0].face, [3, 9]);
    assert_eq!(records[0].points, [0.75, 0.25]);
    // The writer finds the same face: the same bytes back.
    assert_eq!(
        io::encode_payload(&m, Encoding::Structured, false).unwrap(),
        p
    );
}

#[test]
fn reader_errors_are_typed_and_located() {
    let m = Rule::Malformed;
    let faces = Some("/stages/0/faces".to_string());
    let dims = RECORDS + 1;
    let mask = RECORDS + 2;
    let width = RECORDS + 3;
    let with = |at: usize, byte: u8| {
        let mut p = payload_with(&APPENDIX_A_RECORDS);
        p[at] = byte;
        p
    };
    // complexForm other than 0 and 1.
    assert_eq!(
        error_of(&with(COMPLEX_FORM, 2)),
        (m, Some("/vertices".into()), at(COMPLEX_FORM))
    );
    // recordForm above 1.
    assert_eq!(error_of(&with(RECORDS, 2)), (m, faces.clone(), at(RECORDS)));
    // dims with a bit above the dimension (k = 3 in dimension 2).
    assert_eq!(error_of(&with(dims, 0b1010)), (m, faces.clone(), at(dims)));
    // A mask bit past the 3 edges.
    assert_eq!(error_of(&with(mask, 0b1100)), (m, faces.clone(), at(mask)));
    // width above 4.
    assert_eq!(error_of(&with(width, 5)), (m, faces.clone(), at(width)));
    // A monotonic stage (kind 2) with dims ≠ 0.
    assert_eq!(
        error_of(&with(RECORDS - 4, 2)),
        (m, faces.clone(), at(dims))
    );
    // Points that the payload cannot hold: width 0 needs 16 bytes, 15 remain.
    assert_eq!(error_of(&with(width, 0)), (m, faces.clone(), at(width)));
    // Truncated: the payload ends at the mask, at the point, at the weights. (The stage is named
    // so that the payload still holds the 7 bytes a stage takes at least, spec §7.4.1.)
    let named = {
        let mut p = head();
        p.pop();
        p.extend([1, 8]);
        p.extend(b"a stage.");
        p.extend(APPENDIX_A_RECORDS);
        p.extend(tail());
        p
    };
    let shift = 9;
    let cut = |n: usize| named[..n + shift].to_vec();
    let at_shifted = |n: usize| at(n + shift);
    assert_eq!(error_of(&cut(mask)), (m, faces.clone(), at_shifted(mask)));
    assert_eq!(error_of(&cut(width)), (m, faces.clone(), at_shifted(width)));
    assert_eq!(
        error_of(&cut(width + 1)),
        (m, faces.clone(), at_shifted(width))
    );
    let mut rational = cut(width + 2);
    rational[RECORDS - 4] = 1; // kind rational: one weight, 8 bytes, after the point
    rational.extend([0; 7]);
    assert_eq!(error_of(&rational), (m, faces.clone(), at_shifted(width)));
    // A degree of 2^32 − 1: C(d − 1, 1) points per edge record, not allocated; at width.
    let mut p = head();
    p.truncate(p.len() - 3);
    p.extend([0xFC, 0xFF, 0xFF, 0xFF, 0xFF, 0, 0]); // degree u32::MAX, implicit, no name
    let shift = 4; // the degree takes 5 bytes instead of 1
    p.extend(APPENDIX_A_RECORDS);
    p.extend(tail());
    assert_eq!(error_of(&p), (m, faces.clone(), at(width + shift)));
    // Weights the payload cannot hold: a rational stage of three vertex records (k = 0: no
    // point bytes at width 1, one weight each, 24 bytes), with 14 bytes left.
    let mut p = head();
    p.truncate(p.len() - 4);
    p.extend([1, 0xFC, 0xFF, 0xFF, 0xFF, 0xFF, 0, 0]);
    p.extend([1, 0b1, 0b111, 1]);
    p.extend(tail());
    assert_eq!(error_of(&p), (m, faces.clone(), at(width + shift)));
}

#[test]
fn records_by_the_complex_are_refused_outside_dimensions_2_and_3() {
    // dimension 255: one simplex of 256 distinct ids, whose 7-faces no reader lists: recordForm 1
    // is refused at its byte (spec §7.4.3 as amended), before dims.
    let mut p = Vec::new();
    p.extend([3, b'1', b'.', b'0', 255, 0, 0, 0, 0, 0, 0]);
    p.extend([251, 0, 1]); // simplices: 256
    for id in 0u32..256 {
        if id < 251 {
            p.push(id as u8);
        } else {
            p.extend([251, id as u8, 0]);
        }
    }
    p.push(0);
    p.extend(f64s(&[0.0]));
    p.extend([1, 0, 2, 0, 0]);
    let record_form = p.len();
    p.extend([1, 0x80]);
    p.extend(tail());
    let start = std::time::Instant::now();
    assert_eq!(
        error_of(&p),
        (
            Rule::Malformed,
            Some("/stages/0/faces".into()),
            at(record_form)
        )
    );
    assert!(start.elapsed().as_secs() < 5);
    // Dimensions 0, 1 and 4 (an empty complex, a stage without records): at recordForm too, and
    // recordForm 0 reads there.
    for dimension in [0u8, 1, 4] {
        let mut p = vec![3, b'1', b'.', b'0', dimension, 0, 0, 0, 0, 0, 0, 0];
        p.push(0); // values
        p.extend(f64s(&[0.0])); // level
        p.extend([1, 0, 2, 0, 0]); // one stage
        let record_form = p.len();
        let mut q = p.clone();
        p.extend([1, 0, 1]);
        p.extend(tail());
        assert_eq!(
            error_of(&p),
            (
                Rule::Malformed,
                Some("/stages/0/faces".into()),
                at(record_form)
            ),
            "dimension {dimension}"
        );
        q.extend([0, 0]);
        q.extend(tail());
        let m = io::from_slice_with(&file_of(&q), &unchecked())
            .unwrap()
            .model;
        assert_eq!(m.dimension, dimension);
    }
}

#[test]
fn a_mask_past_the_payload_in_3d_is_refused_at_its_first_byte() {
    // dimension 3: the tetrahedron 0 1 2 3 has 6 edges, one mask byte; the payload ends there.
    let mut p = vec![3, b'1', b'.', b'0', 3, 0, 0, 0, 0, 0, 0];
    p.extend([4, 0, 1, 2, 3]); // simplices
    p.push(0); // values
    p.extend(f64s(&[0.0])); // level
    p.extend([1, 0, 2, 0, 1, 2, b'a', b'b']); // one stage, named "ab" (7 bytes at least)
    let mask = p.len() + 2;
    p.extend([1, 0b10]);
    assert_eq!(
        error_of(&p),
        (Rule::Malformed, Some("/stages/0/faces".into()), at(mask))
    );
    // With the mask, edge [2,3] (the last of 6, bit 5) and its lattice point, it reads.
    p.extend([0b10_0000, 1, 64]);
    p.extend(tail());
    let m = io::from_slice_with(&file_of(&p), &unchecked())
        .unwrap()
        .model;
    let records = m.stages[0].faces.to_records();
    assert_eq!(records[0].face, [2, 3]);
    assert_eq!(records[0].points, [0.75, 0.25]);
}

#[test]
fn the_writer_lists_records_outside_dimensions_2_and_3() {
    // An edge record on the complex's own edge, with the counts of its degree: recordForm 1 in
    // 2D, recordForm 0 (listed) in 1D and 4D, and a stage without records too.
    for (dimension, simplex) in [(1u8, vec![0u32, 1]), (4, vec![0, 1, 2, 3, 4])] {
        let mut m = Model::new(dimension);
        m.simplices = simplex;
        m.stages = vec![
            bezier(&[0, 1], &[0.5, 0.5]),
            StageBuilder::monotonic(2).build(),
        ];
        let payload = io::encode_payload(&m, Encoding::Structured, false).unwrap();
        let stage = 4 + 1 + 4 + 1 + 1 + 1 + m.simplices.len() + 1 + 8 + 1;
        assert_eq!(
            &payload[stage..stage + 4],
            [0, 2, 0, 0],
            "dimension {dimension}"
        );
        // recordForm 0, one record [0,1] with two f64, no weights.
        assert_eq!(&payload[stage + 4..stage + 8], [0, 1, 2, 0]);
        let second = stage + 4 + 5 + 1 + 16 + 1 + 1 + 5;
        assert_eq!(&payload[second..second + 5], [2, 2, 0, 0, 0], "{payload:?}");
        let read = io::from_slice_with(
            &io::to_vec(&m, Encoding::Structured, WriteOptions::default()).unwrap(),
            &unchecked(),
        )
        .unwrap()
        .model;
        assert_eq!(read, m);
    }
}

#[test]
fn every_example_round_trips_bit_exactly() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../spec/examples");
    let mut seen = 0;
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if !path.to_string_lossy().ends_with(".ism.json") {
            continue;
        }
        let model = io::read_path(&path).unwrap().model;
        let bytes = io::to_vec(&model, Encoding::Structured, WriteOptions::default()).unwrap();
        let read = io::from_slice(&bytes).unwrap().model;
        assert_eq!(
            io::encode_payload(&read, Encoding::Binary, false).unwrap(),
            io::encode_payload(&model, Encoding::Binary, false).unwrap(),
            "{}",
            path.display()
        );
        // Canonical: what was read writes the same bytes.
        assert_eq!(
            io::to_vec(&read, Encoding::Structured, WriteOptions::default()).unwrap(),
            bytes
        );
        seen += 1;
    }
    assert!(seen > 0);
}

/// A coordinate: on a lattice of some width, or any finite number (±0 and subnormals included).
fn coordinate() -> impl Strategy<Value = f64> {
    prop_oneof![
        (1u32..=4, any::<u32>()).prop_map(|(w, n)| {
            let bits = 8 * w;
            let n = if bits == 32 { n } else { n % (1 << bits) };
            f64::from(n) * f64::powi(2.0, -(bits as i32))
        }),
        any::<u64>()
            .prop_map(f64::from_bits)
            .prop_filter("finite", |x| x.is_finite()),
        Just(-0.0),
    ]
}

/// Models whose records lie on their complex's faces (with the counts of their degree, or not),
/// their points on a lattice or not: every choice of the writer.
fn model() -> impl Strategy<Value = Model> {
    (
        2u8..=3,
        prop::collection::vec(0u32..8, 0..16),
        prop::collection::vec(
            (
                0u8..3,
                1u32..5,
                prop::collection::vec((0usize..8, any::<u64>(), any::<bool>()), 0..6),
                prop::collection::vec(coordinate(), 0..64),
                any::<bool>(),
                (0u8..6, prop::collection::vec(any::<u32>(), 0..64)),
            ),
            0..3,
        ),
    )
        .prop_map(|(dimension, simplices, stages)| {
            let mut m = Model::new(dimension);
            m.simplices = simplices;
            let arity = usize::from(dimension) + 1;
            // The complex's faces, as the spec defines them, written out naively.
            let mut faces: Vec<Vec<u32>> = Vec::new();
            for s in m.simplices.chunks_exact(arity) {
                let mut ids = s.to_vec();
                ids.sort();
                ids.dedup();
                for bits in 1u32..(1 << ids.len()) {
                    faces.push(
                        (0..ids.len())
                            .filter(|i| bits >> i & 1 == 1)
                            .map(|i| ids[i])
                            .collect(),
                    );
                }
            }
            faces.sort_by(|a, b| a.len().cmp(&b.len()).then(a.cmp(b)));
            faces.dedup();
            for (kind, degree, picks, mut numbers, tidy, (mode, mut ints)) in stages {
                let kind = [StageKind::Bezier, StageKind::Rational, StageKind::Monotonic]
                    [usize::from(kind)];
                let mut records: Vec<FaceRecord> = Vec::new();
                let mut chosen: Vec<usize> = Vec::new();
                for (which, seed, exact) in picks {
                    let face = if faces.is_empty() || seed % 7 == 0 {
                        // Sometimes no face of the complex.
                        vec![which as u32, 100]
                    } else {
                        faces[seed as usize % faces.len()].clone()
                    };
                    chosen.push(which);
                    let k = face.len() - 1;
                    let owned = if degree as usize > k {
                        (1..=k as u64)
                            .fold(1u64, |c, i| c * (u64::from(degree) - 1 - k as u64 + i) / i)
                    } else {
                        0
                    } as usize;
                    let count = if exact { owned } else { which % 3 };
                    let mut points = Vec::new();
                    for _ in 0..count {
                        if !(1..=5).contains(&mode) {
                            for _ in 0..=k {
                                points.push(numbers.pop().unwrap_or(0.5));
                            }
                            continue;
                        }
                        // A point of the 2^(-8w) lattice (mode 5: w = 1 with a -0.0), its
                        // integers below 2^(8w), their sum mostly below it too.
                        let w = u32::from(mode.min(4));
                        let scale = 1u64 << (8 * w);
                        let step = f64::powi(2.0, -8 * w as i32);
                        let share = if ints.len() % 5 == 0 {
                            scale
                        } else {
                            scale / (k as u64 + 1)
                        };
                        let n: Vec<u64> = (0..k)
                            .map(|_| u64::from(ints.pop().unwrap_or(7)) % share)
                            .collect();
                        let sum: u64 = n.iter().sum();
                        points.push((scale as i64 - sum as i64) as f64 * step);
                        points.extend(n.iter().map(|&x| x as f64 * step));
                        if mode == 5 && k >= 1 && n[0] == 0 {
                            let last = points.len() - k;
                            points[last] = -0.0;
                        }
                    }
                    let weights = if kind == StageKind::Rational {
                        (0..count).map(|i| 1.0 + i as f64).collect()
                    } else {
                        vec![]
                    };
                    records.push(FaceRecord {
                        face,
                        points,
                        weights,
                    });
                }
                if tidy {
                    // The canonical order of the masks (usually the writer's form 1).
                    records
                        .sort_by(|a, b| a.face.len().cmp(&b.face.len()).then(a.face.cmp(&b.face)));
                    records.dedup_by(|a, b| a.face == b.face);
                }
                let vertex_maps = if kind == StageKind::Monotonic && chosen.len() % 2 == 0 {
                    records.clear();
                    vec![VertexMap {
                        vertex: 0,
                        coefficients: vec![0.0, 1.0],
                    }]
                } else {
                    vec![]
                };
                m.stages.push(Stage {
                    kind,
                    degree,
                    direction: Default::default(),
                    name: None,
                    faces: FaceTable::from(records),
                    vertex_maps,
                    extras: Default::default(),
                });
            }
            m
        })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 500, ..ProptestConfig::default() })]

    /// Bit-exact round trips through `.isms`; canonical (the model read back writes the same
    /// bytes); and the same model in every other encoding.
    #[test]
    fn generated_models_round_trip_bit_exactly(m in model()) {
        let bytes = io::to_vec(&m, Encoding::Structured, WriteOptions::default()).unwrap();
        let read = io::from_slice_with(&bytes, &unchecked()).unwrap().model;
        prop_assert_eq!(
            io::encode_payload(&read, Encoding::Binary, false).unwrap(),
            io::encode_payload(&m, Encoding::Binary, false).unwrap()
        );
        prop_assert_eq!(io::to_vec(&read, Encoding::Structured, WriteOptions::default()).unwrap(), bytes);
    }

    /// Whatever bytes follow a valid head, the reader returns a typed error or a model, never
    /// panics; a model it returns writes back to a file it reads as the same model.
    #[test]
    fn any_records_section_is_read_or_refused(records in prop::collection::vec(any::<u8>(), 0..40)) {
        let mut p = head();
        p.extend(&records);
        p.extend(tail());
        match io::from_slice_with(&file_of(&p), &unchecked()) {
            Ok(doc) => {
                let again = io::to_vec(&doc.model, Encoding::Structured, WriteOptions::default());
                if let Ok(again) = again {
                    let back = io::from_slice_with(&again, &unchecked()).unwrap().model;
                    prop_assert_eq!(
                        io::encode_payload(&back, Encoding::Binary, false).unwrap(),
                        io::encode_payload(&doc.model, Encoding::Binary, false).unwrap()
                    );
                }
            }
            Err(e) => prop_assert!(e.rule().is_some(), "{e}"),
        }
    }
}

/// Structured payloads to mutate: Appendix A's, the writer vector that makes every choice of the
/// writer, the small examples, and files whose complex is `complexForm` 1.
fn seeds() -> Vec<Vec<u8>> {
    let spec = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../spec");
    let mut out = vec![payload_with(&APPENDIX_A_RECORDS)];
    for name in [
        "vectors/writer/structured.isms",
        "vectors/writer/stages.isms",
        "examples/circle-curved.isms",
        "examples/rational-degree5.isms",
        "examples/cubic-face-point.isms",
        "examples/stratified-3d.isms",
    ] {
        let bytes = std::fs::read(spec.join(name)).unwrap();
        out.push(bytes[HEADER_LEN..].to_vec());
    }
    // complexForm 1: the unit square by hand, and two random refinements with a stage.
    out.push(refined_square());
    for seed in [3, 8] {
        let r = random_refinement(seed);
        let (bytes, refined) = io::to_vec_refined(&refined_model(&r), &r).unwrap();
        assert!(refined);
        out.push(bytes[HEADER_LEN..].to_vec());
    }
    out
}

/// One edit of a payload: a byte set, inserted or removed, or the payload cut.
#[derive(Clone, Debug)]
enum Edit {
    Set(usize, u8),
    Insert(usize, u8),
    Remove(usize),
    Cut(usize),
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        4 => (any::<usize>(), any::<u8>()).prop_map(|(i, b)| Edit::Set(i, b)),
        1 => (any::<usize>(), any::<u8>()).prop_map(|(i, b)| Edit::Insert(i, b)),
        1 => any::<usize>().prop_map(Edit::Remove),
        1 => any::<usize>().prop_map(Edit::Cut),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    /// A fuzzer's view (cargo-fuzz's target `read_structured` checks the same on its own inputs):
    /// valid payloads with a few bytes edited are read or refused with a typed, located error,
    /// never a panic; what reads writes back canonically to the same model.
    #[test]
    fn edited_payloads_are_read_or_refused(
        seed in 0usize..10,
        edits in prop::collection::vec(edit(), 1..4),
    ) {
        let mut p = seeds().swap_remove(seed);
        for e in edits {
            let n = p.len().max(1);
            match e {
                Edit::Set(i, b) if !p.is_empty() => p[i % n] = b,
                Edit::Insert(i, b) => p.insert(i % (p.len() + 1), b),
                Edit::Remove(i) if !p.is_empty() => {
                    p.remove(i % n);
                }
                Edit::Cut(i) => p.truncate(i % n),
                _ => {}
            }
        }
        match io::from_slice_with(&file_of(&p), &unchecked()) {
            Ok(doc) => {
                if let Ok(again) = io::to_vec(&doc.model, Encoding::Structured, WriteOptions::default()) {
                    let back = io::from_slice_with(&again, &unchecked()).unwrap().model;
                    prop_assert_eq!(
                        io::encode_payload(&back, Encoding::Binary, false).unwrap(),
                        io::encode_payload(&doc.model, Encoding::Binary, false).unwrap()
                    );
                    prop_assert_eq!(
                        io::to_vec(&back, Encoding::Structured, WriteOptions::default()).unwrap(),
                        again
                    );
                }
            }
            Err(e) => {
                // Every decoding error has its offset, within the file; the version's form and
                // the required extensions are checked after decoding, by JSON pointer (spec §7.8;
                // an inserted byte can turn a string into an unknown extension's name).
                let d = &e.diagnostics()[0];
                match d.location.offset {
                    Some(offset) => prop_assert!(offset <= (HEADER_LEN + p.len()) as u64, "{e}"),
                    None => {
                        let pointer = d.location.pointer.as_deref().unwrap_or("");
                        prop_assert!(
                            pointer == "/version" || pointer.starts_with("/extensionsRequired/"),
                            "{}", e
                        );
                    }
                }
            }
        }
    }
}

/// The unit square with one cube, split on its diagonal, three of its four halves kept (the
/// example of `refine.rs`'s test `the_unit_square_split_on_its_diagonal_by_hand`), in
/// `complexForm` 1, byte by byte. Grid ids 0 (0,0), 1 (1,0), 2 (0,1), 3 (1,1); slots: permutation
/// 01 → (0, 1, 3), permutation 10 (odd) → (0, 2, 3) with its last two swapped → (0, 3, 2).
/// Splitting (0, 3) at m = 4 = (0.5, 0.5) retires both and appends (0, 1, 4), (4, 1, 3) and
/// (0, 4, 2), (4, 3, 2); kept 1011 keeps all but (4, 1, 3): vertex 1 is still used, so no vertex
/// is dropped and the ids stay.
fn refined_square() -> Vec<u8> {
    let mut p = Vec::new();
    p.extend([3, b'1', b'.', b'0']); // 0: version "1.0"
    p.push(2); // 4: dimension
    p.extend([0, 0, 0, 0]); // 5: metadata, all absent
    p.push(1); // 9: complexForm 1
    p.push(4); // 10: box: 4 numbers
    p.extend(f64s(&[0.0, 1.0, 0.0, 1.0])); // 11: lo0 hi0 lo1 hi1
    p.extend([2, 1, 1]); // 43: cells: 2 numbers, 1 and 1
    p.extend([2, 0, 3]); // 46: splits: 2 ids, the pair (0, 3)
    p.push(0b1101); // 49: kept: live slots 0, 2, 3 (bit 1, slot (4, 1, 3), clear)
    p.push(5); // 50: values: 5
    p.extend(f64s(&[-1.0, 1.0, 1.0, 1.0, -0.5]));
    p.extend(f64s(&[0.0])); // level
    p.push(0); // stages: none
    p.extend([0, 0, 0]); // extensionsUsed, extensionsRequired, extensions
    p.extend([4, b'n', b'u', b'l', b'l']); // extras "null"
    p
}

/// Payload offsets in [`refined_square`].
const BOX: usize = 10;
const CELLS: usize = 43;
const SPLITS: usize = 46;
const KEPT: usize = 49;

/// The model [`refined_square`] gives, written out by hand.
fn square_model() -> Model {
    let mut m = Model::new(2);
    m.vertices = vec![0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.5, 0.5];
    m.simplices = vec![0, 1, 4, 0, 4, 2, 4, 3, 2];
    m.values = vec![-1.0, 1.0, 1.0, 1.0, -0.5];
    m
}

fn square_refinement() -> KuhnRefinement {
    KuhnRefinement {
        domain: vec![0.0, 1.0, 0.0, 1.0],
        cells: vec![1, 1],
        splits: vec![[0, 3]],
        kept: vec![true, false, true, true],
    }
}

#[test]
fn a_refined_complex_reads_as_the_construction_by_hand() {
    let doc = io::from_slice(&file_of(&refined_square())).unwrap();
    assert_eq!(doc.encoding, Encoding::Structured);
    assert_eq!(doc.model, square_model());
    // All four kept: vertex 1 used by (4, 1, 3) as well; all halves in slot order.
    let mut p = refined_square();
    p[KEPT] = 0b1111;
    let m = io::from_slice_with(&file_of(&p), &unchecked())
        .unwrap()
        .model;
    assert_eq!(m.simplices, [0, 1, 4, 4, 1, 3, 0, 4, 2, 4, 3, 2]);
    // Only the last two: vertex 1 unused, the ids after it renumbered (3 → 2, 4 → 3).
    p[KEPT] = 0b1100;
    let m = io::from_slice_with(&file_of(&p), &unchecked())
        .unwrap()
        .model;
    assert_eq!(m.vertices, [0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.5, 0.5]);
    assert_eq!(m.simplices, [0, 3, 1, 3, 2, 1]);
    // None kept: an empty complex.
    p[KEPT] = 0;
    let m = io::from_slice_with(&file_of(&p), &unchecked())
        .unwrap()
        .model;
    assert!(m.vertices.is_empty() && m.simplices.is_empty());
}

#[test]
fn refined_complex_errors_are_typed_and_located() {
    let m = Rule::Malformed;
    let vertices = Some("/vertices".to_string());
    let simplices = Some("/simplices".to_string());
    let square = refined_square();
    let with = |at: usize, bytes: &[u8]| {
        let mut p = square.clone();
        p.splice(at..at + bytes.len(), bytes.iter().copied());
        p
    };
    // complexForm 1 outside dimensions 2 and 3: at the byte.
    for dimension in [0, 1, 4] {
        assert_eq!(
            error_of(&with(4, &[dimension])),
            (m, vertices.clone(), at(COMPLEX_FORM - 2))
        );
    }
    // box: the wrong count, lo ≥ hi, an extent that overflows, a sum that would (2 hi is
    // infinite), a NaN — each at the box's first byte, the checks after it is decoded whole.
    let mut three = square[..BOX].to_vec();
    three.push(3);
    three.extend(f64s(&[0.0, 1.0, 0.0]));
    three.extend(&square[CELLS..]);
    assert_eq!(error_of(&three), (m, vertices.clone(), at(BOX)));
    for (k, x) in [(1, 0.0), (0, -f64::MAX), (3, f64::MAX), (2, f64::NAN)] {
        let mut p = square.clone();
        let o = BOX + 1 + 8 * k;
        p[o..o + 8].copy_from_slice(&x.to_le_bytes());
        if k == 0 {
            p[o + 8..o + 16].copy_from_slice(&f64::MAX.to_le_bytes());
        }
        assert_eq!(error_of(&p), (m, vertices.clone(), at(BOX)), "{k} {x}");
    }
    // A box that is wrong and cells that are wrong too: the box first.
    let mut p = three.clone();
    p[BOX + 1 + 24 + 1] = 0;
    assert_eq!(error_of(&p), (m, vertices.clone(), at(BOX)));
    // A box length past the payload: at its length (decoding errors before the checks).
    assert_eq!(error_of(&with(BOX, &[250])), (m, vertices.clone(), at(BOX)));
    // cells: one number for two axes, a zero — at the cells' first byte.
    let mut one = square[..CELLS].to_vec();
    one.extend([1, 1]);
    one.extend(&square[SPLITS..]);
    assert_eq!(error_of(&one), (m, vertices.clone(), at(CELLS)));
    assert_eq!(
        error_of(&with(CELLS, &[2, 0, 1])),
        (m, vertices.clone(), at(CELLS))
    );
    // A cell count as a varint that is not minimal (FB 05 00 for 5): at that varint.
    assert_eq!(
        error_of(&with(CELLS, &[2, 0xFB, 0x05, 0x00])),
        (m, vertices.clone(), at(CELLS + 1))
    );
    // The grid's kept bits: 1000 × 1000 cubes are 2 000 000 simplices, 250 000 bytes of kept
    // bits after cells, which the payload does not hold: at cells, before any grid is built.
    let mut big = square[..CELLS].to_vec();
    big.extend([2, 0xFB, 0xE8, 0x03, 0xFB, 0xE8, 0x03]);
    big.extend(&square[SPLITS..]);
    let start = std::time::Instant::now();
    assert_eq!(error_of(&big), (m, vertices.clone(), at(CELLS)));
    // 2^32 − 1 cubes on both axes: a slot count past u64's kept bytes, the same error (the
    // vertex count, 2^64, would be ISM-007, but the kept bytes come first).
    let mut huge = square[..CELLS].to_vec();
    huge.extend([
        2, 0xFC, 0xFF, 0xFF, 0xFF, 0xFF, 0xFC, 0xFF, 0xFF, 0xFF, 0xFF,
    ]);
    huge.extend(&square[SPLITS..]);
    assert_eq!(error_of(&huge), (m, vertices.clone(), at(CELLS)));
    assert!(start.elapsed().as_secs() < 5);
    // splits: an odd count, at its length — after its varints are decoded (a bad third varint
    // is reported at that varint).
    let mut odd = square[..SPLITS].to_vec();
    odd.extend([3, 0, 3, 1]);
    odd.extend(&square[KEPT..]);
    assert_eq!(error_of(&odd), (m, simplices.clone(), at(SPLITS)));
    odd[SPLITS + 3] = 0xFE;
    assert_eq!(error_of(&odd), (m, simplices.clone(), at(SPLITS + 3)));
    // A pair that is not a split of a live edge: (1, 2) is no edge of the grid, (3, 0) has
    // a > b, (0, 9) names a vertex that does not exist — at the pair's first byte; and after a
    // valid first pair, (0, 3) again (retired) at the second pair.
    for pair in [[1, 2], [3, 0], [0, 9], [0, 0]] {
        assert_eq!(
            error_of(&with(SPLITS + 1, &pair)),
            (m, simplices.clone(), at(SPLITS + 1)),
            "{pair:?}"
        );
    }
    let mut again = square[..SPLITS].to_vec();
    again.extend([4, 0, 3, 0, 3]);
    again.extend(&square[KEPT..]);
    assert_eq!(error_of(&again), (m, simplices.clone(), at(SPLITS + 3)));
    // The per-split bound: splits (0,3) (0,4) (0,5) (0,6) take the live slots from 2 to 4, 6,
    // 8, 10; with one byte after splits, the fourth pair needs two: at that pair.
    let mut fan = square[..SPLITS].to_vec();
    fan.extend([8, 0, 3, 0, 4, 0, 5, 0, 6]);
    fan.push(0xFF);
    assert_eq!(error_of(&fan), (m, simplices.clone(), at(SPLITS + 7)));
    // kept: the payload ends where it starts (no splits: the one byte after cells is the
    // splits' length), at its first byte; a set padding bit (bit 4 of 4 live slots), at its byte.
    let mut short = square[..SPLITS].to_vec();
    short.push(0);
    assert_eq!(error_of(&short), (m, simplices.clone(), at(SPLITS + 1)));
    assert_eq!(
        error_of(&with(KEPT, &[0b1_1101])),
        (m, simplices.clone(), at(KEPT))
    );
    // Two kept bytes (10 live slots after the fan), padding in the second: at the second byte.
    let mut fan = square[..SPLITS].to_vec();
    fan.extend([8, 0, 3, 0, 4, 0, 5, 0, 6]);
    let kept = fan.len();
    fan.extend([0xFF, 0b111]);
    fan.extend(&square[KEPT + 1..]);
    assert_eq!(error_of(&fan), (m, simplices.clone(), at(kept + 1)));
    fan[kept + 1] = 0b11;
    assert!(io::from_slice_with(&file_of(&fan), &unchecked()).is_ok());
}

#[test]
fn the_refined_writer_writes_the_bytes_by_hand_and_falls_back_to_form_0() {
    let model = square_model();
    let (bytes, refined) = io::to_vec_refined(&model, &square_refinement()).unwrap();
    assert!(refined);
    assert_eq!(bytes[12], 6, "encoding tag");
    assert_eq!(&bytes[HEADER_LEN..], &refined_square()[..]);
    assert_eq!(io::from_slice(&bytes).unwrap().model, model);
    // The canonical writer writes complexForm 0, and reads back the same model.
    let canonical = io::to_vec(&model, Encoding::Structured, WriteOptions::default()).unwrap();
    assert_eq!(canonical[HEADER_LEN + COMPLEX_FORM - 2], 0);
    assert_eq!(io::from_slice(&canonical).unwrap().model, model);
    // A refinement of another complex (another kept mask, a split more, another box, a 3D
    // grid), or a model whose vertices differ in one bit: complexForm 0, the canonical file.
    let other = |f: &dyn Fn(&mut KuhnRefinement)| {
        let mut r = square_refinement();
        f(&mut r);
        r
    };
    for r in [
        other(&|r| r.kept = vec![true; 4]),
        other(&|r| {
            r.splits.push([0, 4]);
            r.kept = vec![true; 6];
        }),
        other(&|r| r.domain[1] = 2.0),
        other(&|r| {
            r.domain.extend([0.0, 1.0]);
            r.cells.push(1);
        }),
        other(&|r| r.splits = vec![[1, 2]]),
    ] {
        let (bytes, refined) = io::to_vec_refined(&model, &r).unwrap();
        assert!(!refined, "{r:?}");
        assert_eq!(bytes, canonical);
    }
    let mut moved = model.clone();
    moved.vertices[9] = f64::from_bits(0.5f64.to_bits() + 1);
    let (bytes, refined) = io::to_vec_refined(&moved, &square_refinement()).unwrap();
    assert!(!refined);
    assert_eq!(io::from_slice(&bytes).unwrap().model, moved);
    // -0.0 is not 0.0: the refinement gives +0.0.
    let mut signed = model.clone();
    signed.vertices[0] = -0.0;
    assert!(!io::to_vec_refined(&signed, &square_refinement()).unwrap().1);
    // The atomic file writer: the same bytes, whatever the extension.
    let dir = std::env::temp_dir().join(format!("ism-refined-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("square.ismc");
    assert!(io::write_path_refined(&model, &path, &square_refinement()).unwrap());
    assert_eq!(
        std::fs::read(&path).unwrap(),
        io::to_vec_refined(&model, &square_refinement()).unwrap().0
    );
    assert_eq!(io::read_path(&path).unwrap().model, model);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A refinement of a small random grid in 2D or 3D: splits of live edges found by trying pairs
/// (the construction refuses the others), and a random kept mask.
fn random_refinement(seed: u64) -> KuhnRefinement {
    use ism_format::refine::Refinement;
    let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    let mut next = |m: u64| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state % m
    };
    let n = 2 + next(2) as usize;
    let cells: Vec<u32> = (0..n).map(|_| 1 + next(3) as u32).collect();
    let domain: Vec<f64> = (0..n)
        .flat_map(|k| [-0.3 * k as f64 - 1.0, 0.7 + k as f64 / 3.0])
        .collect();
    let mut r = Refinement::kuhn(&domain, &cells).unwrap();
    let mut splits = Vec::new();
    for _ in 0..300 {
        let nv = r.num_vertices() as u64;
        let a = next(nv) as u32;
        let b = a + 1 + next(6) as u32;
        if r.split(splits.len(), a, b).is_ok() {
            splits.push([a, b]);
        }
        if splits.len() == 25 {
            break;
        }
    }
    let kept = (0..r.live()).map(|_| next(4) != 0).collect();
    KuhnRefinement {
        domain,
        cells,
        splits,
        kept,
    }
}

/// A model on `refinement`'s complex with a value per vertex and a stage with records by the
/// complex.
fn refined_model(refinement: &KuhnRefinement) -> Model {
    let (vertices, simplices) = refinement.model_arrays().unwrap();
    let n = refinement.cells.len();
    let mut m = Model::new(n as u8);
    m.values = (0..vertices.len() / n)
        .map(|v| if v % 2 == 0 { -1.0 } else { 1.0 })
        .collect();
    m.vertices = vertices;
    if let [a, b, ..] = simplices[..] {
        let (a, b) = (a.min(b), a.max(b));
        m.stages = vec![bezier(&[a, b], &[0.75, 0.25])];
    }
    m.simplices = simplices;
    m
}

#[test]
fn refined_files_read_as_the_model_written() {
    let mut splits = 0;
    for seed in 0..40 {
        let r = random_refinement(seed);
        splits += r.splits.len();
        let m = refined_model(&r);
        let (bytes, refined) = io::to_vec_refined(&m, &r).unwrap();
        assert!(refined, "seed {seed}");
        let read = io::from_slice(&bytes).unwrap().model;
        assert_eq!(
            io::encode_payload(&read, Encoding::Binary, false).unwrap(),
            io::encode_payload(&m, Encoding::Binary, false).unwrap(),
            "seed {seed}"
        );
        // Smaller than the listed complex; the canonical writer lists it.
        let canonical = io::to_vec(&read, Encoding::Structured, WriteOptions::default()).unwrap();
        assert!(bytes.len() < canonical.len(), "seed {seed}");
        assert_eq!(io::from_slice(&canonical).unwrap().model, read);
    }
    assert!(splits > 100, "the test's premise: {splits} splits");
}

#[test]
fn the_mutated_seeds_include_refined_complexes() {
    // The edit-based proptest draws from all seeds; three of them are complexForm 1 files (the
    // byte after version, dimension and an empty metadata), in 2D and 3D.
    let seeds = seeds();
    assert_eq!(seeds.len(), 10);
    let refined: Vec<u8> = seeds[7..].iter().map(|p| p[4]).collect();
    assert!(seeds[7..].iter().all(|p| p[9] == 1), "complexForm 1");
    assert!(refined.contains(&2) && refined.contains(&3), "{refined:?}");
}

/// Writes the `complexForm` 1 seeds into the fuzz corpus of `read_structured` (named by their
/// SHA-1 as cargo-fuzz names its inputs) when `ISM_WRITE_FUZZ_SEEDS` is set.
#[test]
fn refined_seeds_for_the_fuzz_corpus() {
    let Some(dir) = std::env::var_os("ISM_WRITE_FUZZ_SEEDS") else {
        return;
    };
    for (i, payload) in seeds()[7..].iter().enumerate() {
        std::fs::write(
            std::path::Path::new(&dir).join(format!("refined-{i}")),
            payload,
        )
        .unwrap();
    }
}
