//! `ism query` end to end: stdin text, NPY in and out, outside points, exit codes.

use std::io::Write;
use std::path::PathBuf;
use std::process::{Command, Stdio};

fn example(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../spec/examples")
        .join(name)
}

fn query(model: &PathBuf, args: &[&str], stdin: &[u8]) -> std::process::Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_ism"))
        .arg("query")
        .arg(model)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    child.stdin.take().unwrap().write_all(stdin).unwrap();
    child.wait_with_output().unwrap()
}

#[test]
fn vertices_give_their_values_and_outside_points_give_minus_one() {
    let path = example("sphere.ism.json");
    let model = ism_format::io::read_path(&path).unwrap().model;
    let v = model.vertex(0).to_vec();
    let input = format!("x,y,z\n{},{},{}\n100,100,100\n", v[0], v[1], v[2]);
    let out = query(&path, &["-"], input.as_bytes());
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next().unwrap(), "x,y,z,simplex,f,sign,gx,gy,gz");
    let first: Vec<f64> = lines
        .next()
        .unwrap()
        .split(',')
        .map(|x| x.parse().unwrap())
        .collect();
    assert!(first[3] >= 0.0);
    assert_eq!(
        first[4], model.values[0],
        "F at a vertex is its value exactly"
    );
    assert_eq!(
        first[5],
        if model.values[0] < model.level {
            -1.0
        } else {
            1.0
        }
    );
    assert!(first[6..9].iter().all(|g| g.is_finite()));
    let second: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(second[3], "-1");
    assert_eq!(second[4], "NaN");
}

#[test]
fn npy_points_in_and_npy_out() {
    let dir = tempfile::tempdir().unwrap();
    let path = example("circle-curved.ism.json");
    // A (3, 2) float64 array.
    let dict = "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 2), }";
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    let pad = (64 - (10 + dict.len() + 1) % 64) % 64;
    bytes.extend_from_slice(&((dict.len() + pad + 1) as u16).to_le_bytes());
    bytes.extend_from_slice(dict.as_bytes());
    bytes.extend(std::iter::repeat_n(b' ', pad));
    bytes.push(b'\n');
    for x in [0.0f64, 0.0, 0.1, 0.2, 9.0, 9.0] {
        bytes.extend_from_slice(&x.to_le_bytes());
    }
    let input = dir.path().join("p.npy");
    std::fs::write(&input, &bytes).unwrap();
    let output = dir.path().join("q.npy");
    let out = query(
        &path,
        &[input.to_str().unwrap(), "-o", output.to_str().unwrap()],
        b"",
    );
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let written = std::fs::read(&output).unwrap();
    let hlen = usize::from(u16::from_le_bytes([written[8], written[9]]));
    let header = String::from_utf8_lossy(&written[10..10 + hlen]);
    assert!(
        header.contains("('simplex', '<i4')") && header.contains("'shape': (3,)"),
        "{header}"
    );
    // Our own reader picks x, y back out of the structured array.
    assert_eq!(
        ism_sample::points::parse_points(&written, 2).unwrap(),
        vec![0.0, 0.0, 0.1, 0.2, 9.0, 9.0]
    );
}

#[test]
fn unreadable_points_exit_2_naming_the_line() {
    let path = example("circle-curved.ism.json");
    let out = query(&path, &["-"], b"0 0\n1 zz\n");
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("line 2"), "{err}");
}
