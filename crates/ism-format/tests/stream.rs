//! The streaming paths against the in-memory ones: `read_with` decodes binary files as they stream
//! in, `write_path` streams the payload to the file; both must give exactly what `from_slice_with`
//! and `to_vec` give for the same bytes and model (the in-memory paths are the ground truth: they
//! check the container before decoding, in the order of spec §7).

use std::io::Read;

use ism_format::builder::{ModelBuilder, StageBuilder};
use ism_format::io::{self, ReadOptions, WriteOptions, HEADER_LEN};
use ism_format::{Document, Encoding, Error, JsonValue, Model};

/// A model with every kind of stage member, and `extras` text longer than the stream's window
/// (256 KiB) so the window has to grow.
fn model(big_extras: bool) -> Model {
    let mut m = ModelBuilder::new(2)
        .name("stream")
        .vertex(&[0.0, 0.0], -1.0)
        .vertex(&[1.0, 0.0], 1.0)
        .vertex(&[1.0, 1.0], 1.0)
        .vertex(&[0.0, 1.0], 1.0)
        .simplex(&[0, 1, 2])
        .simplex(&[0, 2, 3])
        .stage(
            StageBuilder::bezier(2)
                .face(&[0, 2], &[0.6, 0.4], &[])
                .build(),
        )
        .stage(
            StageBuilder::rational(2)
                .face(&[1, 2], &[0.5, 0.5], &[1.5])
                .build(),
        )
        .stage(
            StageBuilder::monotonic(2)
                .vertex_map(1, &[0.0, 0.4, 1.0])
                .build(),
        )
        .build()
        .unwrap();
    if big_extras {
        m.extras = JsonValue(serde_json::json!({ "note": "x".repeat(600_000) }));
    }
    m
}

/// Hands out at most `chunk` bytes per read: every refill path of the stream's window.
struct Chunky<'a> {
    bytes: &'a [u8],
    chunk: usize,
}

impl Read for Chunky<'_> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = buf.len().min(self.chunk).min(self.bytes.len());
        buf[..n].copy_from_slice(&self.bytes[..n]);
        self.bytes = &self.bytes[n..];
        Ok(n)
    }
}

/// What a read gave, comparably: the model, or the rule and every diagnostic's text.
fn outcome(result: Result<Document, Error>) -> Result<Document, String> {
    result.map_err(|e| match &e {
        Error::Io { .. } => format!("io: {e}"),
        _ => format!(
            "{:?}: {}",
            e.rule(),
            e.diagnostics()
                .iter()
                .map(|d| format!("{d} @ {:?}", d.location))
                .collect::<Vec<_>>()
                .join(" | ")
        ),
    })
}

fn assert_same(bytes: &[u8], options: &ReadOptions, what: &str) {
    // A reader holds at most the limit, the header and one byte more (what the in-memory path was
    // always given by `read_with`).
    let cap = options.limits.max_payload_bytes as usize + HEADER_LEN + 1;
    let expected = outcome(io::from_slice_with(&bytes[..bytes.len().min(cap)], options));
    for chunk in [1, 7, 1 << 20] {
        let got = outcome(io::read_with(Chunky { bytes, chunk }, options));
        assert_eq!(got, expected, "{what}, reads of {chunk} bytes");
    }
}

fn refresh_crc(bytes: &mut [u8]) {
    let crc = crc32fast::hash(&bytes[HEADER_LEN..]);
    bytes[24..28].copy_from_slice(&crc.to_le_bytes());
    let hc = crc32fast::hash(&bytes[..28]);
    bytes[28..32].copy_from_slice(&hc.to_le_bytes());
}

#[test]
fn streamed_binary_reads_match_in_memory_reads() {
    let options = ReadOptions::default();
    let bytes = io::to_vec(&model(false), Encoding::Binary, WriteOptions::default()).unwrap();
    assert!(io::from_slice(&bytes).is_ok());
    assert_same(&bytes, &options, "intact");
    for cut in 0..bytes.len() {
        assert_same(&bytes[..cut], &options, &format!("cut at {cut}"));
    }
    for extra in [1usize, 9] {
        let mut long = bytes.clone();
        long.extend(std::iter::repeat_n(0u8, extra));
        assert_same(&long, &options, &format!("{extra} trailing bytes"));
    }
    // Every byte of the payload changed, with the checksums made to fit (decoding errors) and
    // without (checksum mismatch).
    for at in HEADER_LEN..bytes.len() {
        let mut bad = bytes.clone();
        bad[at] ^= 0x5a;
        assert_same(&bad, &options, &format!("byte {at} changed, stale CRC"));
        refresh_crc(&mut bad);
        assert_same(&bad, &options, &format!("byte {at} changed, CRC refreshed"));
    }
    // A payload over the limit, and a limit that cuts the trailing-byte count short.
    let small = ReadOptions {
        limits: io::Limits {
            max_payload_bytes: 40,
            ..io::Limits::default()
        },
        ..ReadOptions::default()
    };
    assert_same(&bytes, &small, "over the limit");
    let mut long = bytes.clone();
    long.extend([1u8; 100]);
    let tight = ReadOptions {
        limits: io::Limits {
            max_payload_bytes: (bytes.len() - HEADER_LEN + 10) as u64,
            ..io::Limits::default()
        },
        ..ReadOptions::default()
    };
    assert_same(&long, &tight, "trailing bytes beyond the limit");
}

#[test]
fn streamed_reads_handle_members_longer_than_the_window() {
    let options = ReadOptions::default();
    let m = model(true);
    let bytes = io::to_vec(&m, Encoding::Binary, WriteOptions::default()).unwrap();
    assert!(bytes.len() > 600_000);
    let doc = io::read_with(
        Chunky {
            bytes: &bytes,
            chunk: 4096,
        },
        &options,
    )
    .unwrap();
    assert_eq!(doc.model, m);
    for cut in [bytes.len() - 1, bytes.len() / 2, 300_000] {
        assert_same(&bytes[..cut], &options, &format!("cut at {cut}"));
    }
}

#[test]
fn streamed_writes_match_in_memory_writes() {
    let dir = tempfile::tempdir().unwrap();
    for big in [false, true] {
        let m = model(big);
        for encoding in Encoding::ALL {
            for options in [
                WriteOptions::default(),
                WriteOptions {
                    pretty: true,
                    json_in_container: true,
                },
            ] {
                let path = dir.path().join(format!("m.{}", encoding.extension()));
                io::write_path(&m, &path, Some(encoding), options).unwrap();
                let expected = io::to_vec(&m, encoding, options).unwrap();
                assert!(
                    std::fs::read(&path).unwrap() == expected,
                    "{encoding:?} {options:?} big extras {big}"
                );
                assert_eq!(io::read_path(&path).unwrap().model, m);
            }
        }
    }
}

/// A 60 × 60 grid of triangles with a record on every edge (10,920 records, ~0.5 MB of payload):
/// records straddle the stream's 256 KiB window, so reads mix the decoder's path for records wholly
/// at hand with its checked path for the rest.
fn grid_with_edge_records() -> Model {
    let n = 60u32;
    let mut b = ModelBuilder::new(2).name("grid");
    for j in 0..=n {
        for i in 0..=n {
            let inside = i + j < n;
            b = b.vertex(
                &[f64::from(i), f64::from(j)],
                if inside { -1.0 } else { 1.0 },
            );
        }
    }
    let id = |i: u32, j: u32| j * (n + 1) + i;
    let mut edges = std::collections::BTreeSet::new();
    for j in 0..n {
        for i in 0..n {
            for t in [
                [id(i, j), id(i + 1, j), id(i + 1, j + 1)],
                [id(i, j), id(i + 1, j + 1), id(i, j + 1)],
            ] {
                b = b.simplex(&t);
                for (a, c) in [(t[0], t[1]), (t[1], t[2]), (t[0], t[2])] {
                    edges.insert((a.min(c), a.max(c)));
                }
            }
        }
    }
    let mut stage = StageBuilder::bezier(2);
    for (k, &(a, c)) in edges.iter().enumerate() {
        let x = 0.4 + 0.2 * (k % 7) as f64 / 7.0;
        stage = stage.face(&[a, c], &[x, 1.0 - x], &[]);
    }
    b.stage(stage.build()).build().unwrap()
}

#[test]
fn streamed_reads_of_many_records_across_the_window() {
    let options = ReadOptions::default();
    let m = grid_with_edge_records();
    assert_eq!(m.stages[0].faces.len(), 10_920);
    let bytes = io::to_vec(&m, Encoding::Binary, WriteOptions::default()).unwrap();
    assert!(bytes.len() > 2 * (1 << 18));
    // Ground truth: the model that was written.
    assert_eq!(io::from_slice(&bytes).unwrap().model, m);
    for chunk in [1, 4093, 1 << 16, 1 << 20] {
        let doc = io::read_with(
            Chunky {
                bytes: &bytes,
                chunk,
            },
            &options,
        )
        .unwrap();
        assert_eq!(doc.model, m, "reads of {chunk} bytes");
    }
    // Cuts and changed bytes inside the records, near and far from window boundaries.
    let records_start = bytes.len() / 4;
    for at in [
        records_start,
        1 << 18,
        (1 << 18) + 5,
        bytes.len() / 2 + 3,
        bytes.len() - 20,
    ] {
        assert_same(&bytes[..at], &options, &format!("cut at {at}"));
        let mut bad = bytes.clone();
        bad[at] ^= 0x5a;
        refresh_crc(&mut bad);
        assert_same(&bad, &options, &format!("byte {at} changed, CRC refreshed"));
    }
}

/// Records of several lengths in one stage, in the three orders a table can take: every record
/// the same (rational edges: points and weights), lengths mixed from the start (cubic edges and
/// triangles by first vertex), and thousands of records of one length followed by one of another
/// (the decoder's run of same-length records must stop there and the table switch to offsets).
fn grid_with_mixed_records() -> (Model, Vec<Vec<ism_format::FaceRecord>>) {
    use ism_format::{FaceRecord, FaceTable, Stage, StageKind};
    let mut m = grid_with_edge_records();
    let edges: Vec<Vec<u32>> = m.stages[0].faces.iter().map(|r| r.face.to_vec()).collect();
    let mut triangles: Vec<Vec<u32>> = m
        .simplex_iter()
        .map(|t| {
            let mut t = t.to_vec();
            t.sort_unstable();
            t
        })
        .collect();
    triangles.sort();
    let edge = |f: &Vec<u32>, k: usize| FaceRecord {
        face: f.clone(),
        points: vec![2.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0, 2.0 / 3.0 + k as f64 * 1e-9],
        weights: vec![],
    };
    let triangle = |f: &Vec<u32>| FaceRecord {
        face: f.clone(),
        points: vec![1.0 / 3.0; 3],
        weights: vec![],
    };
    let rational: Vec<FaceRecord> = edges
        .iter()
        .enumerate()
        .map(|(k, f)| FaceRecord {
            face: f.clone(),
            points: vec![0.5, 0.5],
            weights: vec![1.0 + k as f64 / 1e4],
        })
        .collect();
    let mut mixed: Vec<FaceRecord> = edges
        .iter()
        .enumerate()
        .map(|(k, f)| edge(f, k))
        .chain(triangles.iter().map(triangle))
        .collect();
    mixed.sort_by(|a, b| a.face[0].cmp(&b.face[0]));
    let mut late: Vec<FaceRecord> = edges.iter().enumerate().map(|(k, f)| edge(f, k)).collect();
    late.push(triangle(triangles.last().unwrap()));
    let mut records = vec![m.stages[0].faces.to_records()];
    for (kind, degree, list) in [
        (StageKind::Rational, 2, &rational),
        (StageKind::Bezier, 3, &mixed),
        (StageKind::Bezier, 3, &late),
    ] {
        let mut stage = Stage::identity(kind, degree);
        stage.faces = FaceTable::from(list.clone());
        m.stages.push(stage);
        records.push(list.clone());
    }
    (m, records)
}

#[test]
fn streamed_reads_of_records_of_several_lengths() {
    let options = ReadOptions::default();
    let (m, records) = grid_with_mixed_records();
    assert!(ism_format::structure::check(&m, 10).is_empty());
    let bytes = io::to_vec(&m, Encoding::Binary, WriteOptions::default()).unwrap();
    assert!(bytes.len() > 4 * (1 << 18));
    let read = |chunk: Option<usize>| match chunk {
        None => io::from_slice(&bytes).unwrap().model,
        Some(chunk) => {
            io::read_with(
                Chunky {
                    bytes: &bytes,
                    chunk,
                },
                &options,
            )
            .unwrap()
            .model
        }
    };
    for chunk in [None, Some(1), Some(4093), Some(1 << 16), Some(1 << 20)] {
        let got = read(chunk);
        // Ground truth: the records the stages were built from, as owned lists.
        for (k, list) in records.iter().enumerate() {
            assert_eq!(
                &got.stages[k].faces.to_records(),
                list,
                "stage {k}, reads of {chunk:?}"
            );
        }
        assert_eq!(got, m, "reads of {chunk:?}");
    }
    // One record of other point or weight counts (same face size) inside a run of same-length
    // records: read unchecked it is the record written; checked, the error a read through the
    // checked record path gives (1-byte reads: no record is ever wholly at hand).
    let unchecked = ReadOptions {
        check_structure: false,
        ..ReadOptions::default()
    };
    for (r, points) in [(5000, true), (7000, false)] {
        let mut odd = m.clone();
        odd.stages[1].faces.edit(|recs| {
            if points {
                recs[r].points.push(0.25);
            } else {
                recs[r].weights.clear();
            }
        });
        let mut expected = records[1].clone();
        expected[r] = odd.stages[1].faces.record(r).to_record();
        let odd_bytes = io::to_vec(&odd, Encoding::Binary, WriteOptions::default()).unwrap();
        for chunk in [1, 4093, 1 << 20] {
            let got = io::read_with(
                Chunky {
                    bytes: &odd_bytes,
                    chunk,
                },
                &unchecked,
            )
            .unwrap()
            .model;
            assert_eq!(
                got.stages[1].faces.to_records(),
                expected,
                "record {r}, reads of {chunk}"
            );
        }
        let from_slice = io::from_slice_with(&odd_bytes, &unchecked).unwrap().model;
        assert_eq!(
            from_slice.stages[1].faces.to_records(),
            expected,
            "record {r}"
        );
        assert_same(
            &odd_bytes,
            &options,
            &format!("record {r} of other lengths"),
        );
        assert!(io::from_slice(&odd_bytes).is_err());
    }
    // Cuts and changed bytes in each stage's records (the payload's second half holds them).
    for at in [
        bytes.len() / 3,
        bytes.len() / 2 + 1,
        (3 << 18) + 11,
        bytes.len() * 3 / 4 + 2,
        bytes.len() - 60,
        bytes.len() - 9,
    ] {
        assert_same(&bytes[..at], &options, &format!("cut at {at}"));
        let mut bad = bytes.clone();
        bad[at] ^= 0x21;
        refresh_crc(&mut bad);
        assert_same(&bad, &options, &format!("byte {at} changed, CRC refreshed"));
    }
}

/// A read without the records' numbers (`keep_record_numbers` off, what `ism info` reads) against
/// the full read of the same file (ground truth: the established path, and the model written):
/// every member but the face records' numbers is the same, every table keeps its face ids and
/// lengths, and the outcome of a file with errors (structural, non-finite, cut, changed bytes) is
/// exactly the full read's.
#[test]
fn reads_without_record_numbers_keep_ids_lengths_and_errors() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.ismb");
    let lean = |check: bool| ReadOptions {
        check_structure: check,
        keep_record_numbers: false,
        ..ReadOptions::default()
    };
    let full = |check: bool| ReadOptions {
        check_structure: check,
        ..ReadOptions::default()
    };
    let read = |bytes: &[u8], options: &ReadOptions| {
        std::fs::write(&path, bytes).unwrap();
        outcome(io::read_path_with(&path, options))
    };
    let (mixed, _) = grid_with_mixed_records();
    for m in [mixed, model(true)] {
        let bytes = io::to_vec(&m, Encoding::Binary, WriteOptions::default()).unwrap();
        let got = read(&bytes, &lean(true)).unwrap();
        let want = read(&bytes, &full(true)).unwrap();
        assert_eq!(want.model, m);
        assert_eq!(
            (got.encoding, got.container, got.byte_len),
            (want.encoding, want.container, want.byte_len)
        );
        let (mut a, mut b) = (got.model.clone(), want.model.clone());
        for (k, (s, t)) in a.stages.iter_mut().zip(&mut b.stages).enumerate() {
            let (f, g) = (&s.faces, &t.faces);
            assert!(!f.numbers_kept() && g.numbers_kept(), "stage {k}");
            assert_eq!(f.len(), g.len(), "stage {k}");
            assert_eq!(f.all_face_ids(), g.all_face_ids(), "stage {k}");
            assert_eq!(f.uniform_lengths(), g.uniform_lengths(), "stage {k}");
            assert_eq!(f.face_offsets(), g.face_offsets(), "stage {k}");
            assert_eq!(f.point_offsets(), g.point_offsets(), "stage {k}");
            assert_eq!(f.weight_offsets(), g.weight_offsets(), "stage {k}");
            assert_eq!(f.num_points(), g.all_points().len(), "stage {k}");
            assert_eq!(f.num_weights(), g.all_weights().len(), "stage {k}");
            assert!(f.all_points().is_empty() && f.all_weights().is_empty());
            for r in 0..f.len() {
                let lens =
                    |x: ism_format::FaceRef<'_>| [x.face.len(), x.points.len(), x.weights.len()];
                assert_eq!(
                    f.lengths(r),
                    Some(lens(g.record(r))),
                    "stage {k} record {r}"
                );
                assert_eq!(f.record(r).face, g.face(r));
            }
            assert_eq!(s.parameter_count(), t.parameter_count(), "stage {k}");
            // The rest of the stage is the same.
            s.faces = Default::default();
            t.faces = Default::default();
        }
        assert_eq!(a, b, "members other than the face tables");
        if got.model.stages.iter().any(|s| !s.faces.is_empty()) {
            // Nothing writes or indexes a model read without its numbers.
            let refused = |e: Error| matches!(e, Error::NumbersNotKept { stage: 0, .. });
            assert!(refused(
                io::to_vec(&got.model, Encoding::Binary, WriteOptions::default()).unwrap_err()
            ));
            assert!(refused(io::check_writable(&got.model).unwrap_err()));
            assert!(refused(
                ism_format::IndexedModel::new(got.model.clone()).unwrap_err()
            ));
            assert!(serde_json::to_string(&got.model).is_err());
            let out = dir.path().join("out.ismb");
            assert!(refused(
                io::write_path(
                    &got.model,
                    &out,
                    Some(Encoding::Binary),
                    WriteOptions::default()
                )
                .unwrap_err()
            ));
        }
    }

    let (m, _) = grid_with_mixed_records();
    let bytes = io::to_vec(&m, Encoding::Binary, WriteOptions::default()).unwrap();
    let mut cases: Vec<(String, Vec<u8>)> = Vec::new();
    // Structural errors in a run of same-length records, and in the ragged stage.
    for (k, r, what) in [(1, 5000, "point"), (1, 7000, "weight"), (2, 3, "point")] {
        let mut odd = m.clone();
        odd.stages[k].faces.edit(|recs| match what {
            "point" => recs[r].points.push(0.25),
            _ => recs[r].weights.clear(),
        });
        let bytes = io::to_vec_unchecked(&odd, Encoding::Binary, WriteOptions::default()).unwrap();
        cases.push((
            format!("stage {k} record {r}: one {what} more or less"),
            bytes,
        ));
    }
    // Non-finite numbers: a coordinate of a uniform stage, a weight, one in the ragged stage.
    for (k, r, weight, x) in [
        (0, 10, false, f64::NAN),
        (1, 9000, true, f64::INFINITY),
        (2, 77, false, f64::NEG_INFINITY),
    ] {
        let mut odd = m.clone();
        let rec = odd.stages[k].faces.record_mut(r);
        if weight {
            rec.weights[0] = x;
        } else {
            rec.points[1] = x;
        }
        let bytes = io::to_vec_unchecked(&odd, Encoding::Binary, WriteOptions::default()).unwrap();
        cases.push((
            format!("stage {k} record {r}: {x} (weight {weight})"),
            bytes,
        ));
    }
    // Cuts and changed bytes in the records.
    for at in [bytes.len() / 3, bytes.len() / 2 + 1, bytes.len() - 9] {
        cases.push((format!("cut at {at}"), bytes[..at].to_vec()));
        let mut bad = bytes.clone();
        bad[at] ^= 0x21;
        cases.push((format!("byte {at} changed"), bad.clone()));
        refresh_crc(&mut bad);
        cases.push((format!("byte {at} changed, CRC refreshed"), bad));
    }
    for (what, bytes) in &cases {
        for check in [true, false] {
            let got = read(bytes, &lean(check));
            let want = read(bytes, &full(check));
            match (&got, &want) {
                (Ok(a), Ok(b)) => {
                    // Same records read (the numbers, when kept, checked above).
                    for (s, t) in a.model.stages.iter().zip(&b.model.stages) {
                        assert_eq!(s.faces.all_face_ids(), t.faces.all_face_ids(), "{what}");
                        assert_eq!(s.faces.point_offsets(), t.faces.point_offsets(), "{what}");
                    }
                    // A non-finite number is read again keeping every number.
                    let finite = b.model.stages.iter().all(|s| {
                        s.faces
                            .all_points()
                            .iter()
                            .chain(s.faces.all_weights())
                            .all(|x| x.is_finite())
                    });
                    if !finite {
                        // (Compared bit for bit: NaN is not equal to itself.)
                        let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                        for (s, t) in a.model.stages.iter().zip(&b.model.stages) {
                            assert!(s.faces.numbers_kept(), "{what}");
                            assert!(
                                bits(s.faces.all_points()) == bits(t.faces.all_points())
                                    && bits(s.faces.all_weights()) == bits(t.faces.all_weights()),
                                "{what}"
                            );
                        }
                    }
                }
                _ => assert_eq!(got, want, "{what}, checked {check}"),
            }
        }
        if what.contains(": ") {
            assert!(read(bytes, &full(true)).is_err(), "{what} is an error");
        }
    }
}
