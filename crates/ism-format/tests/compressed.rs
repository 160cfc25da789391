//! The compressed encoding (spec §7.4.2): the payload is the compact payload's length and an xz
//! stream of it — checked with xz's own decoder, not ours; every error of a compact payload is the
//! same error (rule, location, message) behind the compression, the compact reader being the peer;
//! the framing errors are typed and located, the length held to the payload limit.

use std::io::{Read, Write};

use ism_format::io::{self, Limits, ReadOptions, WriteOptions, HEADER_LEN};
use ism_format::{Encoding, Model, Rule};

mod common;
use common::appendix_a;

fn examples() -> Vec<Model> {
    let dir = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../spec/examples");
    let mut out = vec![appendix_a()];
    for name in ["torus", "two-stage", "rational-degree5", "monotonic"] {
        out.push(
            io::read_path(dir.join(format!("{name}.ismb")))
                .unwrap()
                .model,
        );
    }
    out
}

fn container(encoding: Encoding, payload: &[u8]) -> Vec<u8> {
    let mut bytes = io::header(encoding, ism_format::FORMAT_VERSION, payload).to_vec();
    bytes.extend_from_slice(payload);
    bytes
}

/// A compressed file of `compact` declaring `declared` bytes, by xz's own encoder at `preset`.
fn compressed(compact: &[u8], declared: u64, preset: u32) -> Vec<u8> {
    let mut xz = liblzma::write::XzEncoder::new(declared.to_le_bytes().to_vec(), preset);
    xz.write_all(compact).unwrap();
    container(Encoding::Compressed, &xz.finish().unwrap())
}

fn first(bytes: &[u8]) -> (Rule, Option<u64>) {
    let e = io::from_slice(bytes).unwrap_err();
    let d = e.diagnostics().first().unwrap().clone();
    (d.rule, d.location.offset)
}

#[test]
fn the_payload_is_the_compact_length_then_an_xz_stream_of_the_compact_payload() {
    for model in examples() {
        let z = io::to_vec(&model, Encoding::Compressed, WriteOptions::default()).unwrap();
        let c = io::to_vec(&model, Encoding::Compact, WriteOptions::default()).unwrap();
        assert_eq!(z[12], 5, "encoding tag");
        let payload = &z[HEADER_LEN..];
        let declared = u64::from_le_bytes(payload[..8].try_into().unwrap());
        assert_eq!(declared as usize, c.len() - HEADER_LEN);
        // xz's own reader (one stream, nothing after it) gives the compact payload exactly.
        let mut inner = Vec::new();
        let mut reader = liblzma::read::XzDecoder::new(&payload[8..]);
        reader.read_to_end(&mut inner).unwrap();
        assert_eq!(inner, &c[HEADER_LEN..]);
        assert_eq!(reader.total_in() as usize, payload.len() - 8);
        let doc = io::from_slice(&z).unwrap();
        assert_eq!(doc.encoding, Encoding::Compressed);
        assert_eq!(doc.model, io::from_slice(&c).unwrap().model);
        // Streamed read: the same.
        let streamed = io::read_with(std::io::Cursor::new(&z), &ReadOptions::default()).unwrap();
        assert_eq!(streamed.model, doc.model);
        assert!(
            z.len() < c.len() || c.len() < 400,
            "compression did not shrink the file"
        );
    }
}

#[test]
fn every_cut_or_flipped_compact_payload_reads_as_the_compact_file_does() {
    let c = io::to_vec(&appendix_a(), Encoding::Compact, WriteOptions::default()).unwrap();
    let payload = &c[HEADER_LEN..];
    let text = |r: ism_format::Result<io::Document>| match r {
        Ok(d) => Ok(d.model),
        Err(e) => Err(e.to_string()),
    };
    let mut variants: Vec<Vec<u8>> = (0..=payload.len()).map(|n| payload[..n].to_vec()).collect();
    for i in 0..payload.len() {
        for flip in [0x01, 0x80, 0xFF] {
            let mut v = payload.to_vec();
            v[i] ^= flip;
            variants.push(v);
        }
    }
    let mut errors = 0;
    for v in &variants {
        let want = text(io::from_slice(&container(Encoding::Compact, v)));
        errors += usize::from(want.is_err());
        let got = text(io::from_slice(&compressed(v, v.len() as u64, 0)));
        assert_eq!(got, want, "payload {v:02x?}");
    }
    // Every cut short of the whole payload is an error (and so are some flips): the comparison
    // covered errors, not only models.
    assert!(errors > payload.len(), "{errors} errors");
}

#[test]
fn the_uncompressed_length_is_held_to_the_payload_limit_before_decompressing() {
    let c = io::to_vec(&appendix_a(), Encoding::Compact, WriteOptions::default()).unwrap();
    let u = (c.len() - HEADER_LEN) as u64;
    let z = compressed(&c[HEADER_LEN..], u, 6);
    let with_limit = |max| ReadOptions {
        limits: Limits {
            max_payload_bytes: max,
            ..Limits::default()
        },
        ..ReadOptions::default()
    };
    // The compressed payload fits the limit; its uncompressed length does not.
    let compressed_len = (z.len() - HEADER_LEN) as u64;
    assert!(compressed_len < u);
    let e = io::from_slice_with(&z, &with_limit(u - 1)).unwrap_err();
    let d = &e.diagnostics()[0];
    assert_eq!((d.rule, d.location.offset), (Rule::LimitExceeded, Some(32)));
    assert!(io::from_slice_with(&z, &with_limit(u)).is_ok());
    // A length past any limit is refused although the stream is tiny.
    let huge = compressed(&c[HEADER_LEN..], u64::MAX, 6);
    assert_eq!(first(&huge), (Rule::LimitExceeded, Some(32)));
}

#[test]
fn framing_errors_are_typed_and_located() {
    let c = io::to_vec(&appendix_a(), Encoding::Compact, WriteOptions::default()).unwrap();
    let inner = &c[HEADER_LEN..];
    let u = inner.len() as u64;
    let good = compressed(inner, u, 6);
    let end = good.len() as u64;
    // Declared one byte longer, one byte shorter: at the length.
    assert_eq!(
        first(&compressed(inner, u + 1, 6)),
        (Rule::Malformed, Some(32))
    );
    assert_eq!(
        first(&compressed(inner, u - 1, 6)),
        (Rule::Malformed, Some(32))
    );
    // A bomb: 32 MiB of zeros (a few kB of xz) declared as 64 bytes, at the length.
    assert_eq!(
        first(&compressed(&vec![0; 32 << 20], 64, 0)),
        (Rule::Malformed, Some(32))
    );
    // Cut anywhere inside the stream (the container resealed): never a panic, never read. Cut
    // inside the footer: at the end of the payload.
    for cut in 1..good.len() - HEADER_LEN - 8 {
        let short = container(Encoding::Compressed, &good[HEADER_LEN..good.len() - cut]);
        let (rule, offset) = first(&short);
        assert!(matches!(rule, Rule::Malformed), "cut {cut}: {rule:?}");
        if cut <= 12 {
            assert_eq!(offset, Some(short.len() as u64), "cut {cut}");
        }
    }
    // Fewer than 8 bytes: at the end of the payload.
    for n in 0..8 {
        let short = container(Encoding::Compressed, &good[HEADER_LEN..HEADER_LEN + n]);
        assert_eq!(
            first(&short),
            (Rule::Malformed, Some((HEADER_LEN + n) as u64))
        );
    }
    // Stream padding or a second stream after it: at its first byte.
    for tail in [vec![0u8; 4], good[HEADER_LEN + 8..].to_vec()] {
        let mut payload = good[HEADER_LEN..].to_vec();
        payload.extend_from_slice(&tail);
        assert_eq!(
            first(&container(Encoding::Compressed, &payload)),
            (Rule::Malformed, Some(end))
        );
    }
    // Not xz at all: at the stream's first byte.
    let mut payload = u.to_le_bytes().to_vec();
    payload.extend_from_slice(inner);
    assert_eq!(
        first(&container(Encoding::Compressed, &payload)),
        (Rule::Malformed, Some(40))
    );
}

#[test]
fn a_path_ending_in_ismz_is_written_compressed() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.ismz");
    io::write_path(&appendix_a(), &path, None, WriteOptions::default()).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(
        bytes,
        io::to_vec(&appendix_a(), Encoding::Compressed, WriteOptions::default()).unwrap()
    );
    assert_eq!(io::read_path(&path).unwrap().encoding, Encoding::Compressed);
}
