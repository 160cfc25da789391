//! The reference implementation (`ism-format`) behind the protocol of `tools/conformance`:
//!
//! ```text
//! ism-conformance-adapter read FILE...               per file, one line: {"ok": true} or {"rule", "location"};
//!                                                    exit 0 when every file reads, else 1
//! ism-conformance-adapter convert IN OUT ENCODING    ENCODING: json, json-pretty, msgpack, binary
//! ```
//!
//! `ism` itself prints messages for people; this prints the first diagnostic as data so that any
//! implementation can be compared with the vectors of `spec/vectors/`.

use std::process::ExitCode;

use ism_format::io::{self, WriteOptions};
use ism_format::{Encoding, Error};

fn report(error: &Error) -> ExitCode {
    match error.diagnostics().first() {
        Some(d) => {
            let out = serde_json::json!({"rule": d.rule.id(), "location": d.location, "message": d.message});
            println!("{out}");
            ExitCode::from(1)
        }
        None => {
            eprintln!("ism-conformance-adapter: {error}");
            ExitCode::from(2)
        }
    }
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args
        .iter()
        .map(String::as_str)
        .collect::<Vec<_>>()
        .as_slice()
    {
        // Several files: one line each (the differential test of tests/python reads whole corpora).
        ["read", files @ ..] if !files.is_empty() => {
            let mut status = ExitCode::SUCCESS;
            for file in files {
                match io::read_path(file) {
                    Ok(_) => println!("{}", serde_json::json!({"ok": true})),
                    Err(e) => status = report(&e),
                }
            }
            status
        }
        ["convert", input, output, encoding] => {
            let (encoding, pretty) = match *encoding {
                "json" => (Encoding::Json, false),
                "json-pretty" => (Encoding::Json, true),
                "msgpack" => (Encoding::MessagePack, false),
                "binary" => (Encoding::Binary, false),
                "compact" => (Encoding::Compact, false),
                "compressed" => (Encoding::Compressed, false),
                "structured" => (Encoding::Structured, false),
                other => {
                    eprintln!(
                        "unknown encoding {other:?}; expected json, json-pretty, msgpack, binary, compact, compressed or structured"
                    );
                    return ExitCode::from(2);
                }
            };
            let options = WriteOptions {
                pretty,
                json_in_container: false,
            };
            match io::read_path(input)
                .and_then(|doc| io::write_path(&doc.model, output, Some(encoding), options))
            {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => report(&e),
            }
        }
        _ => {
            eprintln!("usage: ism-conformance-adapter read FILE | convert IN OUT json|json-pretty|msgpack|binary|compact|compressed|structured");
            ExitCode::from(2)
        }
    }
}
