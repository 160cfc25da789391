//! Re-encode a model: `cargo run -p ism-format --example convert -- IN OUT`.
//! The input encoding is sniffed from content; the output encoding follows the extension.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, output] = args.as_slice() else {
        return Err("usage: convert IN OUT".into());
    };
    let doc = ism_format::io::read_path(input)?;
    ism_format::io::write_path(&doc.model, output, None, Default::default())?;
    println!("{input} ({}) -> {output}", doc.encoding.name());
    Ok(())
}
