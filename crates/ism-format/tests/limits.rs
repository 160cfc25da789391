//! Entity limits (`io::Limits`, spec §7.6): a count above a limit is ISM-007 at the member's
//! pointer, in every encoding and on the streamed binary path; a count equal to its limit reads.
//! The counts come from the JSON text itself (`serde_json::Value`), not from the reader.

use std::io::Read;
use std::path::PathBuf;

use ism_format::io::{self, Limits, ReadOptions};
use ism_format::{Error, Rule};

fn example(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(format!("../../spec/examples/{name}"))
}

/// `(vertices, simplices, stages, records of each stage)` counted from the JSON text.
fn counts(name: &str) -> (u64, u64, u64, Vec<u64>) {
    let text = std::fs::read_to_string(example(&format!("{name}.ism.json"))).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let n = v["dimension"].as_u64().unwrap();
    let len = |x: &serde_json::Value| x.as_array().map_or(0, |a| a.len() as u64);
    let stages = v["stages"].as_array().cloned().unwrap_or_default();
    (
        len(&v["vertices"]) / n,
        len(&v["simplices"]) / (n + 1),
        stages.len() as u64,
        stages
            .iter()
            .map(|s| len(&s["faces"]) + len(&s["vertexMaps"]))
            .collect(),
    )
}

/// Every way a file is read: in memory from each encoding, and streamed from the binary file.
fn read_all(name: &str, limits: Limits) -> Vec<Result<(), Error>> {
    let options = ReadOptions {
        limits,
        ..ReadOptions::default()
    };
    let mut out = Vec::new();
    for ext in ["ism.json", "ism.msgpack", "ismb"] {
        let bytes = std::fs::read(example(&format!("{name}.{ext}"))).unwrap();
        out.push(io::from_slice_with(&bytes, &options).map(|_| ()));
        out.push(io::from_slice_indexed(&bytes, &options).map(|_| ()));
    }
    let file = std::fs::File::open(example(&format!("{name}.ismb"))).unwrap();
    out.push(io::read_with(file, &options).map(|_| ()));
    out
}

fn assert_limit(results: &[Result<(), Error>], pointer: &str, field: &str) {
    for r in results {
        let Err(Error::Format(d)) = r else {
            panic!("expected ISM-007 at {pointer}, got {r:?}");
        };
        assert_eq!(d.rule, Rule::LimitExceeded, "{d:?}");
        assert_eq!(d.location.pointer.as_deref(), Some(pointer), "{d:?}");
        assert!(d.message.contains(field), "{}", d.message);
    }
}

#[test]
fn each_entity_limit_is_enforced_at_its_member_in_every_encoding() {
    for name in ["sphere", "stratified-3d", "monotonic", "two-stage"] {
        let (vertices, simplices, stages, records) = counts(name);
        let total: u64 = records.iter().sum();
        // Exactly at every limit: reads.
        let exact = Limits {
            max_vertices: vertices,
            max_simplices: simplices,
            max_stages: stages,
            max_records: total,
            ..Limits::default()
        };
        for r in read_all(name, exact) {
            r.unwrap_or_else(|e| panic!("{name} at its own counts: {e}"));
        }
        // One below each: refused there.
        let below = |l: Limits| read_all(name, l);
        assert_limit(
            &below(Limits {
                max_vertices: vertices - 1,
                ..exact
            }),
            "/vertices",
            "max_vertices",
        );
        assert_limit(
            &below(Limits {
                max_simplices: simplices - 1,
                ..exact
            }),
            "/simplices",
            "max_simplices",
        );
        if stages > 0 {
            assert_limit(
                &below(Limits {
                    max_stages: stages - 1,
                    ..exact
                }),
                "/stages",
                "max_stages",
            );
        }
        if total > 0 {
            // The stage whose records pass the limit is named.
            let last = records.iter().rposition(|&r| r > 0).unwrap();
            assert_limit(
                &below(Limits {
                    max_records: total - 1,
                    ..exact
                }),
                &format!("/stages/{last}"),
                "max_records",
            );
        }
    }
}

#[test]
fn the_default_limits_read_every_example() {
    for entry in std::fs::read_dir(example("")).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() {
            io::read_path_with(&path, &ReadOptions::default())
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        }
    }
}

/// The payload limit on every encoding, in memory and streamed: a container's declared payload
/// above it is ISM-007 at offset 16; a JSON text without a container is all payload, so one byte
/// over the limit is ISM-007 at the limit's offset on both paths (the stream holds the text cut
/// short, which must not surface as a parse error at the cut). A payload equal to the limit reads.
/// The payload lengths come from the container header's bytes 16..24 and the file size.
#[test]
fn payload_limit_is_the_same_error_in_memory_and_streamed() {
    for ext in ["ism.json", "ism.msgpack", "ismb"] {
        let bytes = std::fs::read(example(&format!("two-stage.{ext}"))).unwrap();
        let container = bytes.starts_with(b"\x89ISM\r\n\x1a\n");
        let payload = if container {
            u64::from_le_bytes(bytes[16..24].try_into().unwrap())
        } else {
            bytes.len() as u64
        };
        for (limit, refused) in [(payload, false), (payload - 1, true), (payload / 2, true)] {
            let options = ReadOptions {
                limits: Limits {
                    max_payload_bytes: limit,
                    ..Limits::default()
                },
                ..ReadOptions::default()
            };
            let results = [
                io::from_slice_with(&bytes, &options).map(|_| ()),
                io::read_with(bytes.as_slice(), &options).map(|_| ()),
                io::read_with(std::io::Cursor::new(&bytes).take(u64::MAX), &options).map(|_| ()),
            ];
            for r in &results {
                if !refused {
                    assert!(r.is_ok(), "{ext} at the limit {limit}: {r:?}");
                    continue;
                }
                let Err(Error::Format(d)) = r else {
                    panic!("{ext}, limit {limit}: expected ISM-007, got {r:?}");
                };
                assert_eq!(d.rule, Rule::LimitExceeded, "{ext}: {d:?}");
                let at = if container { 16 } else { limit };
                assert_eq!(d.location.offset, Some(at), "{ext}: {d:?}");
            }
        }
    }
}
