//! The errors of `validate_path` keep their cause as `source()` and print it once: the wrapper's
//! message gives the context, [`ErrorChain`] adds each cause after it.

use ism_format::ErrorChain;
use ism_validate::{validate_path, Error, Options};

#[test]
fn a_missing_file_names_the_path_and_the_os_error_once() {
    let dir = std::env::temp_dir().join(format!("ism-validate-errors-{}", std::process::id()));
    let path = dir.join("absent.ism.json");
    let err = validate_path(&path, &Options::default()).unwrap_err();
    let Error::Io { source, .. } = &err else {
        panic!("expected Error::Io, got {err:?}");
    };
    // Truth: the operating system's own message for the same failure.
    let os = std::fs::read(&path).unwrap_err().to_string();
    assert_eq!(source.to_string(), os);
    assert_eq!(err.to_string(), format!("cannot read {}", path.display()));
    let chain = ErrorChain(&err).to_string();
    assert_eq!(chain, format!("cannot read {}: {os}", path.display()));
}

#[test]
fn unreadable_bytes_keep_the_readers_diagnostic_as_source() {
    let dir = std::env::temp_dir().join(format!("ism-validate-errors-b-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("garbage.ismb");
    std::fs::write(&path, b"ISMB but not really a container").unwrap();
    let err = validate_path(&path, &Options::default()).unwrap_err();
    std::fs::remove_dir_all(&dir).unwrap();
    let Error::Read(read) = &err else {
        panic!("expected Error::Read, got {err:?}");
    };
    assert!(!read.diagnostics().is_empty(), "{read:?}");
    let inner = read.to_string();
    assert_eq!(err.to_string(), "unreadable");
    let chain = ErrorChain(&err).to_string();
    assert_eq!(chain, format!("unreadable: {inner}"));
    assert_eq!(chain.matches(&inner).count(), 1, "{chain}");
}
