//! `spec/schema/ism.schema.json` is generated from the types; this fails when the two drift apart.
//! Regenerate with `BLESS=1 cargo test -p ism-format --test schema`.

use std::path::PathBuf;

#[test]
fn checked_in_schema_matches_the_types() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../spec/schema/ism.schema.json");
    let generated = serde_json::to_string_pretty(&ism_format::json_schema()).unwrap() + "\n";
    if std::env::var_os("BLESS").is_some() {
        std::fs::write(&path, &generated).unwrap();
    }
    let stored = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        stored == generated,
        "spec/schema/ism.schema.json is out of date; run BLESS=1 cargo test -p ism-format --test schema"
    );
}
