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
