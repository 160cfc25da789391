//! Issue 16, item 7: on a terminal every long command names its phases (no time-left estimate);
//! `-q` silences them; off a terminal nothing is drawn.
#![cfg(unix)]

mod common;

use std::io::Read;
use std::process::Output;

use common::{assert_status, example, ism};

/// Runs `ism ARGS` with standard error on a pseudo-terminal; returns the output and what was
/// drawn on the terminal.
fn on_terminal(args: &[&str]) -> (Output, String) {
    let (mut controller, terminal) = common::pseudo_terminal();
    // Read while the command runs, so a full terminal buffer never blocks it.
    let reader = std::thread::spawn(move || {
        let mut seen = Vec::new();
        let mut buf = [0u8; 4096];
        // Linux reports EIO once the last writer has closed the terminal side.
        while let Ok(k) = controller.read(&mut buf) {
            if k == 0 {
                break;
            }
            seen.extend_from_slice(&buf[..k]);
        }
        String::from_utf8_lossy(&seen).into_owned()
    });
    let mut command = ism();
    command.args(args).stderr(terminal);
    let out = command.output().unwrap();
    drop(command);
    (out, reader.join().unwrap())
}

#[test]
fn long_commands_name_their_phases_and_q_silences_them() {
    let dir = tempfile::tempdir().unwrap();
    let sphere = example("sphere.ism.json");
    let sphere = sphere.to_str().unwrap();
    let obj = dir.path().join("s.obj");
    let obj = obj.to_str().unwrap();
    let bin = dir.path().join("s.ismb");
    let bin = bin.to_str().unwrap();
    let smoothed = dir.path().join("c.ism.json");
    let circle = example("circle-curved.ism.json");
    let circle = circle.to_str().unwrap();
    let cases: [(Vec<&str>, &[&str]); 6] = [
        (
            vec!["export", sphere, obj],
            &["reading", "extracting the curved shape", "writing"],
        ),
        (
            vec!["validate", sphere],
            &["validating", "positivity certificates"],
        ),
        (
            vec![
                "sample",
                sphere,
                "--surface",
                "2000",
                "-o",
                "/dev/null",
                "--format",
                "csv",
            ],
            &["measuring the curved area", "sampling", "points"],
        ),
        (vec!["convert", sphere, bin], &["reading", "writing"]),
        (vec!["info", sphere], &["reading", "summarizing"]),
        (
            vec![
                "smooth",
                circle,
                "-o",
                smoothed.to_str().unwrap(),
                "--iterations",
                "1",
            ],
            &["smoothing", "validating the output"],
        ),
    ];
    for (args, phases) in cases {
        let (out, drawn) = on_terminal(&args);
        assert_status(&out, 0);
        for phase in phases {
            assert!(drawn.contains(phase), "{args:?}: no {phase:?} in {drawn:?}");
        }
        assert!(!drawn.contains("eta"), "{args:?}: {drawn:?}");
        let mut quiet = args.clone();
        quiet.push("-q");
        let (out, drawn) = on_terminal(&quiet);
        assert_status(&out, 0);
        for phase in phases {
            assert!(!drawn.contains(phase), "{quiet:?}: {phase:?} in {drawn:?}");
        }
    }
}

#[test]
fn nothing_is_drawn_off_a_terminal() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("s.obj");
    let out = ism()
        .arg("export")
        .arg(example("sphere.ism.json"))
        .arg(&obj)
        .output()
        .unwrap();
    assert_status(&out, 0);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("extracting"), "{stderr}");
}
