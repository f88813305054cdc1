//! The command line as a user runs it: the main job, `detect` with JSON, and the refusal to
//! overwrite files.

use std::path::Path;
use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_fluid-surfels"))
}

fn data(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
        .display()
        .to_string()
}

#[test]
fn main_job_writes_surface_ply_and_picture() {
    let dir = tempfile::tempdir().unwrap();
    let out = bin()
        .args(["run", "--out-dir"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("particles          2880"), "{stdout}");
    let surface = fluid_surfels::io::read_particles(&dir.path().join("surface.ply"), None).unwrap();
    assert!(
        surface.len() > 500 && surface.len() < 2880,
        "{}",
        surface.len()
    );
    let normals = surface.normals.as_ref().unwrap();
    assert!(normals.iter().all(|n| (n.length() - 1.0).abs() < 1e-3));
    let picture = image::open(dir.path().join("classes.png"))
        .unwrap()
        .to_rgb8();
    assert_eq!(picture.dimensions(), (800, 800));
    // the picture shows surface-coloured pixels (orange: red high, blue low)
    let orange = picture.pixels().filter(|p| p[0] > 150 && p[2] < 60).count();
    assert!(orange > 10_000, "{orange} orange pixels");
}

#[test]
fn detect_prints_json_statistics() {
    let out = bin()
        .args(["detect", "--scene", "block", "--json"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["particles"], 21_952);
    let c = &v["counts"];
    let sum = c["interior"].as_u64().unwrap()
        + c["surface"].as_u64().unwrap()
        + c["isolated"].as_u64().unwrap();
    assert_eq!(sum, 21_952);
    // 28^3 block: exactly its outer layer, 28^3 - 26^3
    assert_eq!(c["surface"], 28 * 28 * 28 - 26 * 26 * 26);
    for phase in ["read", "neighbours", "classify", "normals", "write"] {
        assert!(v["timings_ms"][phase].as_f64().unwrap() >= 0.0, "{phase}");
    }
}

#[test]
fn detect_on_a_file_estimates_the_radius_and_never_overwrites() {
    let dir = tempfile::tempdir().unwrap();
    let out_path = dir.path().join("surface.ply");
    let run = |extra: &[&str]| {
        bin()
            .args(["detect", "--input", &data("cube_normals.ply"), "--out"])
            .arg(&out_path)
            .args(extra)
            .args(["--json"])
            .output()
            .unwrap()
    };
    let first = run(&[]);
    assert!(
        first.status.success(),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&first.stdout).unwrap();
    assert_eq!(v["spacing_estimate"], 2.0);
    let written = std::fs::read(&out_path).unwrap();
    // a second run refuses to replace the file, and leaves it as it was
    let second = run(&[]);
    assert!(!second.status.success());
    assert!(String::from_utf8_lossy(&second.stderr).contains("--force"));
    assert_eq!(std::fs::read(&out_path).unwrap(), written);
    assert!(run(&["--force"]).status.success());
    // the input itself is never an output
    let input = dir.path().join("in.ply");
    std::fs::copy(data("cube.ply"), &input).unwrap();
    let same = bin()
        .args(["detect", "--force", "--input"])
        .arg(&input)
        .arg("--out")
        .arg(&input)
        .output()
        .unwrap();
    assert!(!same.status.success());
    assert_eq!(
        std::fs::read(&input).unwrap(),
        std::fs::read(data("cube.ply")).unwrap()
    );
}

#[test]
fn bad_input_gives_a_clear_error_and_no_panic() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.xyz");
    std::fs::write(&bad, "0 0 0\n1 nan 1\n").unwrap();
    let out = bin()
        .args(["detect", "--input"])
        .arg(&bad)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("bad.xyz") && err.contains("line 2") && err.contains("non-finite"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    let out = bin()
        .args(["detect", "--scene", "block", "--radius=-1"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("radius"));
    let out = bin()
        .args(["detect", "--scene", "sphere", "--frame", "3"])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("static"));
}

#[test]
fn bench_detect_reports_the_reference_ratio() {
    let out = bin()
        .args([
            "bench",
            "detect",
            "--particles",
            "5000",
            "--repeat",
            "1",
            "--json",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(v["speedup"].as_f64().unwrap() > 0.0);
    assert_eq!(v["classes_agree_with_reference"], true);
    assert!(v["particles"].as_u64().unwrap() >= 5000);
}
