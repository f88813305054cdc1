//! The command line as a user runs it: the main job, `detect` with JSON, and the refusal to
//! overwrite files.

use std::path::Path;
use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_fluid-surfels"))
}

/// Asserts that a run succeeded, showing its stderr otherwise.
fn succeeded(out: &std::process::Output) {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The JSON object a successful `--json` run printed.
fn json_of(out: &std::process::Output) -> serde_json::Value {
    succeeded(out);
    serde_json::from_slice(&out.stdout).expect("--json prints one JSON object")
}

fn data(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data")
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
    succeeded(&out);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("particles          2880"), "{stdout}");
    for file in [
        "surface.ply",
        "refined.ply",
        "surfels.ply",
        "classes.png",
        "refine.png",
        "surfels.png",
        "splats.png",
        "frame.png",
        "caustics.png",
        "stages.png",
    ] {
        assert!(dir.path().join(file).exists(), "{file}");
    }
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
    let v = json_of(&out);
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
    let v = json_of(&first);
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
    let v = json_of(&out);
    assert!(v["speedup"].as_f64().unwrap() > 0.0);
    assert_eq!(v["classes_agree_with_reference"], true);
    assert!(v["particles"].as_u64().unwrap() >= 5000);
}

/// Twenty frames of 150,000 particles each (jittered blocks that grow frame by frame).
fn write_sequence(dir: &Path) {
    for f in 0..20u64 {
        let scene = fluid_surfels::scenes::block(&fluid_surfels::scenes::BlockParams {
            counts: [60, 50, 50],
            seed: f,
            ..Default::default()
        })
        .unwrap();
        let path = dir.join(format!("ParticleData_Fluid_{f}.ply"));
        fluid_surfels::io::write_particles(&path, &scene.particles, None).unwrap();
    }
}

fn outputs(dir: &Path) -> Vec<(String, std::time::SystemTime)> {
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with("surface_"))
        .map(|e| {
            (
                e.file_name().to_string_lossy().into_owned(),
                e.metadata().unwrap().modified().unwrap(),
            )
        })
        .collect();
    v.sort();
    v
}

#[test]
fn sequences_run_in_parallel_and_resume_after_a_kill() {
    let dir = tempfile::tempdir().unwrap();
    write_sequence(dir.path());
    let input = format!("{}/ParticleData_Fluid_{{}}.ply", dir.path().display());
    let out_dir = dir.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let out = format!("{}/surface_{{:04}}.ply", out_dir.display());
    let args = |extra: &[&str]| {
        let mut c = bin();
        c.args([
            "detect", "--input", &input, "--out", &out, "--frames", "0..20", "--jobs", "2",
            "--radius", "0.1",
        ]);
        c.args(extra);
        c
    };
    // start, and kill it once a few frames are written
    let mut child = args(&[])
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    while outputs(&out_dir).len() < 4 && std::time::Instant::now() < deadline {
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let done = outputs(&out_dir);
    println!("killed after {} of 20 frames", done.len());
    assert!(
        done.len() >= 4 && done.len() < 20,
        "{} outputs when killed",
        done.len()
    );
    // every output present is complete (written atomically)
    for (name, _) in &done {
        let s = fluid_surfels::io::read_particles(&out_dir.join(name), None).unwrap();
        assert!(s.len() > 10_000, "{name}: {}", s.len());
    }
    // without --skip-existing or --force, nothing is overwritten
    let refused = args(&[]).output().unwrap();
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("--skip-existing"));
    assert_eq!(outputs(&out_dir), done);
    // resume: the rest is done, the frames already written are left untouched
    std::thread::sleep(std::time::Duration::from_millis(20));
    let resumed = args(&["--skip-existing", "--json"]).output().unwrap();
    let v = json_of(&resumed);
    assert_eq!(v["skipped"].as_array().unwrap().len(), done.len());
    assert_eq!(v["processed"].as_u64().unwrap() as usize, 20 - done.len());
    let after = outputs(&out_dir);
    assert_eq!(after.len(), 20);
    for (name, time) in &done {
        let now = after.iter().find(|(n, _)| n == name).unwrap();
        assert_eq!(now.1, *time, "{name} was rewritten");
    }
    assert_eq!(after[0].0, "surface_0000.ply");
    assert_eq!(after[19].0, "surface_0019.ply");
    // every frame of the blocks has its outer layer as surface: 60x50x50 - 58x48x48
    let last = fluid_surfels::io::read_particles(&out_dir.join("surface_0019.ply"), None).unwrap();
    assert_eq!(last.len(), 60 * 50 * 50 - 58 * 48 * 48);
}

#[test]
fn info_describes_a_file() {
    let out = bin()
        .args([
            "info",
            &data("double_dam_break_frame_26_4732_particles.vtk"),
            "--json",
        ])
        .output()
        .unwrap();
    let v = json_of(&out);
    assert_eq!(v["format"], "vtk");
    assert_eq!(v["particles"], 4732);
    let names: Vec<&str> = v["attributes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["id", "velocity"]);
    assert_eq!(v["attributes"][0]["max"], 4731.0);
    assert!(v["spacing_estimate"].as_f64().unwrap() > 0.03);
    let text = bin()
        .args(["info", &data("cube_normals.ply")])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&text.stdout);
    assert!(
        text.contains("particles  24") && text.contains("normal"),
        "{text}"
    );
    // a sequence: one entry per frame
    let dir = tempfile::tempdir().unwrap();
    for f in [3, 4, 5] {
        std::fs::copy(data("cube.ply"), dir.path().join(format!("c_{f:03}.ply"))).unwrap();
    }
    let pattern = format!("{}/c_{{:03}}.ply", dir.path().display());
    let out = bin()
        .args(["info", &pattern, "--json", "--jobs", "2"])
        .output()
        .unwrap();
    let v = json_of(&out);
    let frames: Vec<u64> = v
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["frame"].as_u64().unwrap())
        .collect();
    assert_eq!(frames, [3, 4, 5]);
    assert!(v.as_array().unwrap().iter().all(|f| f["particles"] == 24));
    // a file that is not what its extension says
    let dir = tempfile::tempdir().unwrap();
    let fake = dir.path().join("fake.vtk");
    std::fs::copy(data("cube.ply"), &fake).unwrap();
    let out = bin().arg("info").arg(&fake).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("found a PLY file"));
}

#[test]
fn bench_io_reports_every_format() {
    let out = bin()
        .args([
            "bench",
            "io",
            "--particles",
            "2000",
            "--repeat",
            "1",
            "--json",
        ])
        .output()
        .unwrap();
    let v = json_of(&out);
    let formats = v["formats"].as_array().unwrap();
    assert_eq!(formats.len(), 8);
    for f in formats {
        assert!(f["particles_per_second"].as_f64().unwrap() > 0.0, "{f}");
    }
}

#[test]
fn refine_reports_steps_and_writes_points() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("refined.ply");
    let png = dir.path().join("refine.png");
    let run = bin()
        .args([
            "refine", "--scene", "column", "--frame", "14", "--json", "--out",
        ])
        .arg(&out)
        .arg("--png")
        .arg(&png)
        .output()
        .unwrap();
    let v = json_of(&run);
    let steps = v["steps"].as_array().unwrap();
    assert_eq!(steps.len(), 3);
    for s in steps {
        for key in [
            "points_after",
            "candidates",
            "collisions_type2",
            "collisions_type3",
            "resolved",
            "ms",
        ] {
            assert!(s[key].is_number(), "{key} in {s}");
        }
    }
    let points = v["points"].as_u64().unwrap();
    assert_eq!(points, steps[2]["points_after"].as_u64().unwrap());
    let set = fluid_surfels::io::read_particles(&out, None).unwrap();
    assert_eq!(set.len() as u64, points);
    for name in ["step", "weight", "radius"] {
        assert!(set.attribute(name).is_some(), "{name}");
    }
    assert_eq!(image::open(&png).unwrap().width(), 1400);
    // the reference implementation gives the same points
    let out2 = dir.path().join("reference.ply");
    let run = bin()
        .args([
            "refine",
            "--scene",
            "column",
            "--frame",
            "14",
            "--reference",
            "--out",
        ])
        .arg(&out2)
        .output()
        .unwrap();
    assert!(run.status.success());
    assert_eq!(
        fluid_surfels::io::read_particles(&out2, None)
            .unwrap()
            .positions,
        set.positions
    );
    // refining the output of `detect` directly
    let surface = dir.path().join("surface.ply");
    assert!(
        bin()
            .args(["detect", "--scene", "block", "--out"])
            .arg(&surface)
            .output()
            .unwrap()
            .status
            .success()
    );
    let run = bin()
        .args([
            "refine",
            "--surface-input",
            "--radius",
            "0.1",
            "--steps",
            "1",
            "--json",
            "--input",
        ])
        .arg(&surface)
        .output()
        .unwrap();
    let v = json_of(&run);
    assert!(v["points"].as_u64().unwrap() > v["p0"].as_u64().unwrap());
}

#[test]
fn bench_refine_reports_table_1_frames() {
    let out = bin()
        .args(["bench", "refine", "--repeat", "1", "--json"])
        .output()
        .unwrap();
    let v = json_of(&out);
    let frames = v["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 3);
    for f in frames {
        for key in [
            "name",
            "p0",
            "p3",
            "seconds",
            "points_per_second",
            "reference_points_per_second",
            "speedup",
        ] {
            assert!(!f[key].is_null(), "{key} in {f}");
        }
    }
}

/// `bench refine --input`: both implementations on a real file, each in a child process, with
/// the same points and each one's peak memory; a bad file is a clear error naming it.
#[test]
fn bench_refine_on_a_file_measures_each_implementation_apart() {
    let out = bin()
        .args([
            "bench", "refine", "--steps", "2", "--repeat", "1", "--json", "--input",
        ])
        .arg(data("double_dam_break_frame_26_4732_particles.vtk"))
        .output()
        .unwrap();
    let v = json_of(&out);
    let runs = v["runs"].as_array().unwrap();
    assert_eq!(runs.len(), 2);
    assert_eq!(runs[0]["implementation"], "parallel");
    assert_eq!(runs[1]["implementation"], "reference");
    let points = runs[0]["points"].as_u64().unwrap();
    assert!(points > 4732, "{points} points");
    assert_eq!(runs[1]["points"].as_u64(), Some(points));
    if cfg!(target_os = "linux") {
        for r in runs {
            let mib = r["peak_rss_mib"].as_f64().unwrap();
            assert!(mib > 1.0 && mib < 4096.0, "{mib} MiB");
        }
    }
    let bad = bin()
        .args([
            "bench",
            "refine",
            "--repeat",
            "1",
            "--input",
            "no_such_file.vtk",
        ])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("no_such_file.vtk"), "{err}");
}

#[test]
fn bench_density_compares_with_the_naive_reference() {
    let out = bin()
        .args([
            "bench",
            "density",
            "--particles",
            "3000",
            "--resolution",
            "40",
            "--json",
        ])
        .output()
        .unwrap();
    let v = json_of(&out);
    assert_eq!(v["particles"], 3000);
    assert_eq!(v["grid"], serde_json::json!([40, 40, 40]));
    assert!(v["cpu_density_ms"].as_f64().unwrap() > 0.0);
    assert!(v["naive_density_ms"].as_f64().unwrap() > 0.0);
    // with an adapter (lavapipe in CI) the GPU path is timed and agrees with the CPU
    if v["gpu_density_ms"].is_null() {
        assert!(std::env::var("FLUID_SURFELS_REQUIRE_GPU").map_or(true, |v| v != "1"));
    } else {
        assert!(v["gpu_difference_from_cpu"].as_f64().unwrap() <= 1e-4);
    }
    assert!(v["cpu_extract_ms"].as_f64().unwrap() > 0.0);
    assert!(v["surfels"].as_u64().unwrap() > 100);
    assert!(v["max_difference_from_naive"].as_f64().unwrap() <= 1e-4);
}

#[test]
fn surfels_command_writes_surfels_on_cpu_and_gpu() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("surfels.ply");
    let run = bin()
        .args([
            "surfels",
            "--scene",
            "sphere",
            "--resolution",
            "48",
            "--json",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    let v = json_of(&run);
    let dims: Vec<u64> = v["grid"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| d.as_u64().unwrap())
        .collect();
    assert_eq!(
        dims.iter().max(),
        Some(&48),
        "the longest axis has the resolution asked for: {dims:?}"
    );
    let n = v["surfels"].as_u64().unwrap();
    assert!(n > 1000, "{n}");
    let set = fluid_surfels::io::read_particles(&out, None).unwrap();
    assert_eq!(set.len() as u64, n);
    assert!(set.attribute("radius").is_some() && set.normals.is_some());
    // the GPU path gives the same surfels, or a clear error without an adapter
    let gpu = bin()
        .args([
            "surfels",
            "--scene",
            "sphere",
            "--resolution",
            "48",
            "--json",
            "--gpu",
        ])
        .output()
        .unwrap();
    if gpu.status.success() {
        let g: serde_json::Value = serde_json::from_slice(&gpu.stdout).unwrap();
        assert_eq!(g["path"], "gpu");
        let m = g["surfels"].as_u64().unwrap() as f64;
        assert!(
            (m - n as f64).abs() <= 0.001 * n as f64,
            "gpu {m} vs cpu {n} surfels"
        );
    } else {
        let err = String::from_utf8_lossy(&gpu.stderr);
        assert!(err.contains("GPU") && !err.contains("panicked"), "{err}");
        assert!(
            std::env::var("FLUID_SURFELS_REQUIRE_GPU").map_or(true, |v| v != "1"),
            "a GPU is required here: {err}"
        );
    }
}

/// `surfels --steps N` (and `--source`, `--calibration`): the library pipeline's surfels (issue
/// 35), the same count as `Pipeline` with those parameters gives; `--gpu` and `--h`, which
/// only the raw density grid takes, are refused with them.
#[test]
fn surfels_takes_the_chains_steps_source_and_calibration() {
    use fluid_surfels::pipeline::{Calibration, Pipeline, PipelineParams, SurfelSource, Through};
    let set = ddb_set();
    let radius = fluid_surfels::neighbours::support_radius(&set.positions).unwrap();
    let input = data("double_dam_break_frame_26_4732_particles.vtk");
    for (args, source, steps, calibration) in [
        (
            vec!["--steps", "1"],
            SurfelSource::Chain,
            1,
            Calibration::Boundary,
        ),
        (
            vec!["--source", "particles", "--calibration", "paper"],
            SurfelSource::Particles,
            3,
            Calibration::Paper,
        ),
    ] {
        let v = json_of(
            &bin()
                .args(["surfels", "--json", "--input", &input])
                .args(&args)
                .output()
                .unwrap(),
        );
        let mut p = PipelineParams {
            support_radius: Some(radius),
            source,
            ..PipelineParams::default()
        };
        p.refine.steps = steps;
        p.grid.calibration = calibration;
        let frame = Pipeline::new(p)
            .unwrap()
            .frame_through(&set, Through::Surfels)
            .unwrap();
        let n = frame.surfels.unwrap().len() as u64;
        assert!(n > 1000, "{v}");
        assert_eq!(v["surfels"].as_u64(), Some(n), "{args:?}: {v}");
        assert_eq!(v["pipeline"]["source"], source.as_str(), "{v}");
        assert_eq!(v["pipeline"]["calibration"], calibration.as_str(), "{v}");
        if source == SurfelSource::Chain {
            assert_eq!(v["pipeline"]["steps"], steps, "{v}");
        }
    }
    for bad in [
        &["--steps", "2", "--gpu"][..],
        &["--source", "chain", "--h", "0.1"],
    ] {
        let err = stderr_of(
            &bin()
                .args(["surfels", "--input", &input])
                .args(bad)
                .output()
                .unwrap(),
        );
        assert!(
            err.contains("cannot be used with") && !err.contains("panicked"),
            "{err}"
        );
    }
}

#[test]
fn render_draws_particles_and_users_surfels_and_refuses_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("sphere.png");
    let v = json_of(
        &bin()
            .args([
                "render",
                "--scene",
                "sphere",
                "--resolution",
                "40",
                "--size",
                "96x64",
                "--cpu",
                "--json",
                "--out",
            ])
            .arg(&png)
            .output()
            .unwrap(),
    );
    assert_eq!(v["backend"], "cpu reference");
    assert_eq!(v["surfel_source"], "chain");
    assert_eq!(
        (v["width"].as_u64(), v["height"].as_u64()),
        (Some(96), Some(64))
    );
    // every surfel source renders the sphere; the refined points are drawn as they are
    let mut counts = Vec::new();
    for source in ["particles", "refined"] {
        let out = dir.path().join(format!("{source}.png"));
        let v = json_of(
            &bin()
                .args([
                    "render", "--scene", "sphere", "--size", "64x64", "--cpu", "--json",
                ])
                .args(["--source", source, "--out"])
                .arg(&out)
                .output()
                .unwrap(),
        );
        assert_eq!(v["surfel_source"], source);
        assert!(v["covered_pixels"].as_u64().unwrap() > 500, "{source}: {v}");
        counts.push(v["surfels"].as_u64().unwrap());
    }
    assert_ne!(counts[0], counts[1]);
    let covered = v["covered_pixels"].as_u64().unwrap();
    assert!(covered > 800 && covered < 96 * 64, "{covered}");
    let picture = image::open(&png).unwrap().to_rgb8();
    assert_eq!(picture.dimensions(), (96, 64));
    // the sphere is water blue in the middle
    let centre = picture.get_pixel(48, 32);
    assert!(centre[2] > centre[0] + 40, "{centre:?}");
    // a user's own surfels: a PLY with normals and radius
    let surfels = dir.path().join("own.ply");
    let mut set = fluid_surfels::ParticleSet::from_positions(vec![glam::Vec3::ZERO, glam::Vec3::X]);
    set.normals = Some(vec![glam::Vec3::Z; 2]);
    set.extra.push(fluid_surfels::Attribute::scalar(
        "radius",
        fluid_surfels::ScalarKind::F32,
        vec![0.4, 0.4],
    ));
    fluid_surfels::io::write_particles(&surfels, &set, None).unwrap();
    let own_png = dir.path().join("own.png");
    let v = json_of(
        &bin()
            .args([
                "render",
                "--size",
                "64x64",
                "--cpu",
                "--json",
                "--camera",
                "0.5,0,3,0.5,0,0",
                "--surfels",
            ])
            .arg(&surfels)
            .arg("--out")
            .arg(&own_png)
            .output()
            .unwrap(),
    );
    assert_eq!(v["surfels"], 2);
    assert!(v["covered_pixels"].as_u64().unwrap() > 100);
    // refusals: an existing output, surfels without radius, a bad size
    let again = bin()
        .args(["render", "--size", "64x64", "--cpu", "--surfels"])
        .arg(&surfels)
        .arg("--out")
        .arg(&own_png)
        .output()
        .unwrap();
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("--force"));
    set.extra.clear();
    let no_radius = dir.path().join("no-radius.ply");
    fluid_surfels::io::write_particles(&no_radius, &set, None).unwrap();
    for args in [
        vec!["--surfels".to_string(), no_radius.display().to_string()],
        vec![
            "--scene".into(),
            "sphere".into(),
            "--size".into(),
            "0x10".into(),
        ],
        vec![
            "--scene".into(),
            "sphere".into(),
            "--camera".into(),
            "1,2,3".into(),
        ],
    ] {
        let out = bin()
            .arg("render")
            .args(&args)
            .arg("--out")
            .arg(dir.path().join("x.png"))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && !err.contains("panicked"),
            "{args:?}: {err}"
        );
        println!("{args:?}: {err}");
    }
}

#[test]
fn bench_splat_reports_rates_and_agreement() {
    let v = json_of(
        &bin()
            .args([
                "bench",
                "splat",
                "--surfels",
                "20000",
                "--size",
                "160x120",
                "--repeat",
                "1",
                "--json",
            ])
            .output()
            .unwrap(),
    );
    assert_eq!(v["surfels"], 20000);
    assert!(v["cpu_splats_per_second"].as_f64().unwrap() > 0.0);
    assert!(v["covered_pixels"].as_u64().unwrap() > 5000);
    match v["gpu"].as_object() {
        Some(g) => {
            assert!(g["splats_per_second"].as_f64().unwrap() > 0.0);
            // null when the images are identical
            assert!(
                g["psnr_against_cpu_db"].as_f64().is_none_or(|p| p >= 40.0),
                "{g:?}"
            );
            assert!(g["max_difference_from_cpu"].as_u64().unwrap() < 64, "{g:?}");
        }
        None => assert!(
            std::env::var("FLUID_SURFELS_REQUIRE_GPU").map_or(true, |v| v != "1"),
            "a GPU is required here"
        ),
    }
}

#[test]
fn render_optics_writes_frames_and_refuses_bad_scenes() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene.toml");
    std::fs::write(
        &scene,
        "[light]\ndirection = [0.2, 1.0, 0.1]\n\n[water]\nextinction = [2.0, 0.6, 0.3]\n\n[receiver]\nchecker = 0.05\n",
    )
    .unwrap();
    let out = dir.path().join("one.png");
    let run = bin()
        .args([
            "render",
            "--scene",
            "column",
            "--frame",
            "3",
            "--size",
            "96x64",
            "--caustics-resolution",
            "64x64",
            "--cpu",
            "--json",
            "--config",
        ])
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let report = json_of(&run);
    assert_eq!(report["screen"], serde_json::json!([64, 64]));
    assert!(
        report["caustics_triangles"].as_u64().unwrap() > 100,
        "{report}"
    );
    let flux = report["map_flux"][0].as_f64().unwrap();
    assert!(flux > 0.0 && flux <= report["incident_flux"][0].as_f64().unwrap());
    assert_eq!(image::open(&out).unwrap().to_rgb8().dimensions(), (96, 64));
    // a sequence into a folder, then refused without --force
    let frames = dir.path().join("frames");
    let seq = || {
        bin()
            .args([
                "render",
                "--scene",
                "column",
                "--frames",
                "1..3",
                "--size",
                "48x48",
                "--caustics-resolution",
                "32x32",
                "--cpu",
                "--out",
            ])
            .arg(&frames)
            .output()
            .unwrap()
    };
    succeeded(&seq());
    for f in [1, 2] {
        assert!(frames.join(format!("frame_{f:04}.png")).exists());
    }
    assert!(!seq().status.success());
    // bad scene files: typed errors, nothing written
    std::fs::write(&scene, "[water]\nior = -3.0\n").unwrap();
    let bad = dir.path().join("bad.png");
    let run = bin()
        .args(["render", "--scene", "column", "--cpu", "--config"])
        .arg(&scene)
        .arg("--out")
        .arg(&bad)
        .output()
        .unwrap();
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("ior"));
    assert!(!bad.exists());
}

#[test]
fn bench_optics_reports_json() {
    let run = bin()
        .args([
            "bench",
            "optics",
            "--surfels",
            "2000",
            "--size",
            "64x64",
            "--repeat",
            "1",
            "--json",
        ])
        .output()
        .unwrap();
    let report = json_of(&run);
    let cases = report["cases"].as_array().unwrap();
    assert_eq!(cases.len(), 2);
    assert!(
        cases
            .iter()
            .all(|c| c["cpu_caustics_ms"].as_f64().unwrap() > 0.0)
    );
}

/// `bench renderers` times every renderer on the CPU and, where there is an adapter, on the
/// GPU, with the two images in agreement; `--particles` resamples the body first.
#[test]
fn bench_renderers_times_every_renderer_on_both_backends() {
    let gpu = fluid_surfels::gpu::context_or_skip("bench renderers on the GPU")
        .unwrap()
        .is_some();
    let mut cmd = bin();
    cmd.args(["bench", "renderers", "--size", "48x48", "--repeat", "1"])
        .args([
            "--input",
            &data("double_dam_break_frame_26_4732_particles.vtk"),
        ])
        .args(["--particles", "8000", "--json"]);
    if !gpu {
        cmd.arg("--no-gpu");
    }
    let v = json_of(&cmd.output().unwrap());
    let n = v["particles"].as_u64().unwrap();
    assert!((7000..=9000).contains(&n), "{v}");
    let rows = v["renderers"].as_array().unwrap();
    let names: Vec<&str> = rows
        .iter()
        .map(|r| r["renderer"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["ewa", "particle-splat", "ray-cast"]);
    for r in rows {
        assert!(r["cpu_ms"].as_f64().unwrap() > 0.0, "{r}");
        assert!(r["covered_pixels"].as_u64().unwrap() > 100, "{r}");
        if gpu {
            assert!(r["gpu_ms"].as_f64().unwrap() > 0.0, "{r}");
            let psnr = r["psnr_gpu_against_cpu_db"]
                .as_f64()
                .unwrap_or(f64::INFINITY);
            assert!(psnr >= 40.0, "{r}");
        }
    }
}

/// `bench lnm` reports the band of a block and the one-thread reference of the same run.
#[test]
fn bench_lnm_reports_the_band_and_the_reference() {
    let v = json_of(
        &bin()
            .args([
                "bench",
                "lnm",
                "--particles",
                "20000",
                "--repeat",
                "1",
                "--json",
            ])
            .output()
            .unwrap(),
    );
    let (n, band) = (
        v["particles"].as_u64().unwrap(),
        v["band"].as_u64().unwrap(),
    );
    assert!(n >= 19_000 && band > 0 && band < n, "{v}");
    assert!(v["median_ms"].as_f64().unwrap() > 0.0, "{v}");
    assert!(v["one_thread_ms"].as_f64().unwrap() > 0.0, "{v}");
    assert!(v["layer_1_voxels"].as_u64().unwrap() > 0, "{v}");
}

#[test]
fn bench_pipeline_reports_every_stage() {
    let v = json_of(
        &bin()
            .args([
                "bench", "pipeline", "--frame", "4", "--size", "48x48", "--repeat", "1", "--json",
            ])
            .output()
            .unwrap(),
    );
    assert_eq!(v["frame"], 4);
    assert!(v["surfels"].as_u64().unwrap() > 1000, "{v}");
    let stages = &v["stages_ms"];
    for stage in [
        "refine_ms",
        "density_ms",
        "surfels_ms",
        "caustics_ms",
        "image_ms",
    ] {
        assert!(stages[stage].as_f64().unwrap() > 0.0, "{stage}: {v}");
    }
    assert!(v["median_ms"].as_f64().unwrap() >= stages["refine_ms"].as_f64().unwrap());
}

/// A software rasteriser (lavapipe) is no default: `render` takes the CPU reference unless
/// `--gpu` asks for the GPU path; a hardware adapter is the default.
#[test]
fn render_takes_a_software_adapter_only_when_asked() {
    let dir = tempfile::tempdir().unwrap();
    let run = |extra: &[&str], name: &str| {
        json_of(
            &bin()
                .args(["render", "--scene", "sphere", "--size", "48x48", "--json"])
                .args(extra)
                .arg("--out")
                .arg(dir.path().join(name))
                .output()
                .unwrap(),
        )
    };
    let default = run(&[], "default.png");
    match fluid_surfels::gpu::GpuContext::headless() {
        Ok(ctx) => {
            let software = ctx.adapter.as_ref().is_some_and(|a| a.is_software());
            let backend = default["backend"].as_str().unwrap().to_owned();
            assert_eq!(backend == "cpu reference", software, "{backend}");
            let asked = run(&["--gpu"], "gpu.png");
            assert!(
                asked["backend"].as_str().unwrap().starts_with("gpu"),
                "{asked}"
            );
        }
        Err(_) => assert_eq!(default["backend"], "cpu reference"),
    }
}

/// `render` on a copy of the double dam break in `dir`, with `extra` arguments.
fn render_ddb(dir: &Path, extra: &[&str]) -> std::process::Output {
    render_input(&dir.join("ddb.vtk"), extra)
}

/// `render --renderer R` of the double dam break in `dir` (64x48, the particles source), the
/// shaded splats or the finished frame (its virtual screen 64x64), on the GPU and on the CPU:
/// the PSNR between the two PNGs, after checking that each report names its backend.
fn gpu_against_cpu(dir: &Path, renderer: &str, optics: bool) -> f64 {
    let draw = |backend: &str| {
        let out = dir.join(format!("{renderer}{backend}{optics}.png"));
        let report = json_of(
            &bin()
                .args(["render", "--renderer", renderer, "--json", backend])
                .args(["--size", "64x48", "--source", "particles", "--input"])
                .arg(dir.join("ddb.vtk"))
                // a small virtual screen: at the default (256 texels) lavapipe casts the
                // light's view for 10 s, at 64 for 2 s
                .args(
                    optics
                        .then_some(["--optics", "--caustics-resolution", "64x64"])
                        .into_iter()
                        .flatten(),
                )
                .arg("--out")
                .arg(&out)
                .output()
                .unwrap(),
        );
        (report, image::open(&out).unwrap().to_rgba8())
    };
    let ((gpu, a), (cpu, b)) = (draw("--gpu"), draw("--cpu"));
    assert!(gpu["backend"].as_str().unwrap().starts_with("gpu"), "{gpu}");
    assert_eq!(cpu["backend"], "cpu reference", "{cpu}");
    fluid_surfels::splat::psnr(&a, &b)
}

/// `render` of `input`, small, on the CPU, the raw particles' surface, with `extra` arguments.
fn render_input(input: &Path, extra: &[&str]) -> std::process::Output {
    bin()
        .args([
            "render",
            "--cpu",
            "--size",
            "64x48",
            "--source",
            "particles",
        ])
        .arg("--input")
        .arg(input)
        .args(extra)
        .output()
        .unwrap()
}

/// A folder holding a copy of the double dam break as `ddb.vtk`, for [`render_ddb`].
fn ddb_dir() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(
        data("double_dam_break_frame_26_4732_particles.vtk"),
        dir.path().join("ddb.vtk"),
    )
    .unwrap();
    dir
}

/// The double dam break's particles.
fn ddb_set() -> fluid_surfels::ParticleSet {
    fluid_surfels::io::read_particles(
        Path::new(&data("double_dam_break_frame_26_4732_particles.vtk")),
        None,
    )
    .unwrap()
}

fn stderr_of(out: &std::process::Output) -> String {
    assert!(!out.status.success(), "expected a failure");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn render_papercuts_fail_early_with_what_to_do() {
    let dir = ddb_dir();
    let d = dir.path();
    // a missing output folder is refused before any work
    let missing = d.join("no/such/folder/out.png");
    let e = stderr_of(&render_ddb(d, &["--out", missing.to_str().unwrap()]));
    assert!(
        e.contains("does not exist") && e.contains("nothing was done"),
        "{e}"
    );
    let e = stderr_of(&render_ddb(
        d,
        &["--optics", "--out", missing.to_str().unwrap()],
    ));
    assert!(e.contains("does not exist"), "{e}");
    // an existing file: --force is the way out, --skip-existing is for sequences
    let out = d.join("one.png");
    std::fs::write(&out, b"mine").unwrap();
    let e = stderr_of(&render_ddb(d, &["--out", out.to_str().unwrap()]));
    assert!(
        e.contains("--force") && !e.contains("--skip-existing"),
        "{e}"
    );
    assert_eq!(std::fs::read(&out).unwrap(), b"mine");
    let e = stderr_of(&render_ddb(
        d,
        &["--skip-existing", "--out", out.to_str().unwrap()],
    ));
    assert!(e.contains("sequences"), "{e}");
    let e = stderr_of(&render_ddb(
        d,
        &["--skip-existing", "--force", "--out", "x.png"],
    ));
    assert!(e.contains("cannot be used with"), "{e}");
    // a pattern without --frames says what to add
    let e = stderr_of(
        &bin()
            .args(["render", "--cpu", "--input"])
            .arg(d.join("frame_{}.vtk"))
            .output()
            .unwrap(),
    );
    assert!(e.contains("--frames"), "{e}");
    // bad colours and axes are refused by the parser
    let e = stderr_of(&render_ddb(d, &["--background", "1,2", "--out", "x.png"]));
    assert!(e.contains("R,G,B"), "{e}");
    let e = stderr_of(&render_ddb(d, &["--up", "w", "--out", "x.png"]));
    assert!(e.contains("-z"), "{e}");
}

/// `render --renderer particle-splat` draws every particle of the `particles` source as a
/// sphere of the support radius: the PNG is the library's particle splatting of those spheres
/// from the camera the report gives.
#[test]
fn render_draws_particle_spheres_with_the_particle_splat_renderer() {
    let dir = ddb_dir();
    let d = dir.path();
    let out = d.join("spheres.png");
    let report = json_of(&render_ddb(
        d,
        &[
            "--renderer",
            "particle-splat",
            "--json",
            "--out",
            out.to_str().unwrap(),
        ],
    ));
    assert_eq!(report["renderer"], "particle-splat", "{report}");
    assert_eq!(report["mode"], "spheres", "{report}");
    let set = ddb_set();
    assert_eq!(report["surfels"].as_u64().unwrap(), set.len() as u64);
    let camera: fluid_surfels::splat::Camera =
        serde_json::from_value(report["camera"].clone()).unwrap();
    let radius = fluid_surfels::neighbours::support_radius(&set.positions).unwrap();
    let spheres = fluid_surfels::splat::spheres_from(
        &set.positions,
        &[],
        radius,
        fluid_surfels::splat::WATER,
    );
    let params = fluid_surfels::splat::SplatParams {
        mode: fluid_surfels::splat::SplatMode::Spheres,
        ..Default::default()
    };
    let expected = fluid_surfels::splat::render_cpu(
        &spheres,
        &camera,
        &fluid_surfels::splat::Light::default(),
        &params,
        64,
        48,
    )
    .unwrap();
    assert!(expected.covered_pixels() > 200);
    let png = image::open(&out).unwrap().to_rgba8();
    assert_eq!(
        png, expected.image,
        "the PNG is not the library's particle splatting"
    );
    // the ray caster's report names it
    let report = json_of(&render_ddb(
        d,
        &[
            "--renderer",
            "ray-cast",
            "--json",
            "--out",
            d.join("rays.png").to_str().unwrap(),
        ],
    ));
    assert_eq!(report["renderer"], "ray-cast", "{report}");
    assert_eq!(report["backend"], "cpu reference", "{report}");
    assert!(report["covered_pixels"].as_u64().unwrap() > 200, "{report}");
    // the GPU twin: --gpu casts there, the same pictures, shaded and finished
    if fluid_surfels::gpu::context_or_skip("render --renderer ray-cast --gpu")
        .unwrap()
        .is_some()
    {
        for optics in [false, true] {
            let psnr = gpu_against_cpu(d, "ray-cast", optics);
            assert!(
                psnr >= 35.0,
                "optics {optics}: GPU against CPU ray casting {psnr:.1} dB"
            );
        }
    }
    // sprites are a mode of the EWA renderer
    let e = stderr_of(&render_ddb(
        d,
        &[
            "--renderer",
            "particle-splat",
            "--sprites",
            "--out",
            "x.png",
        ],
    ));
    assert!(e.contains("cannot be used with"), "{e}");
}

/// `compare` on the column scene at a small size: a 4x3 contact sheet, and a JSON report with
/// every renderer and source against the ray-cast reference (which the ray-cast method of the
/// same points meets exactly in depth and coverage: only its normals are filtered).
#[test]
fn compare_reports_every_method_against_the_reference() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sheet.png");
    let run = |extra: &[&str]| {
        bin()
            .args(["compare", "--scene", "column", "--size", "64x48", "--out"])
            .arg(&out)
            .args(extra)
            .output()
            .unwrap()
    };
    let report = json_of(&run(&["--json"]));
    let methods = report["methods"].as_array().unwrap();
    let names: Vec<String> = methods
        .iter()
        .map(|m| {
            format!(
                "{}/{}",
                m["renderer"].as_str().unwrap(),
                m["source"].as_str().unwrap()
            )
        })
        .collect();
    for renderer in ["ewa", "particle-splat", "ray-cast", "ssfr"] {
        for source in ["chain", "particles"] {
            assert!(names.contains(&format!("{renderer}/{source}")), "{names:?}");
        }
    }
    assert_eq!(methods.len(), 11, "{names:?}");
    for m in methods {
        let d = &m["against_reference"];
        for key in [
            "depth_mean",
            "depth_p95",
            "normal_mean_degrees",
            "normal_p95_degrees",
            "coverage_difference",
        ] {
            assert!(d[key].as_f64().is_some_and(f64::is_finite), "{key} of {m}");
        }
        assert!(
            m["ms"].as_f64().unwrap() > 0.0 && m["covered_pixels"].as_u64().unwrap() > 0,
            "{m}"
        );
    }
    let same = methods
        .iter()
        .find(|m| m["renderer"] == "ray-cast" && m["source"] == "particles")
        .unwrap();
    assert_eq!(
        same["against_reference"]["depth_mean"].as_f64(),
        Some(0.0),
        "{same}"
    );
    assert_eq!(
        same["against_reference"]["coverage_difference"].as_f64(),
        Some(0.0),
        "{same}"
    );
    let sheet = image::open(&out).unwrap();
    assert_eq!((sheet.width(), sheet.height()), (4 * 64, 3 * 48));
    // the sheet is not replaced without --force, and a bad size is refused by the parser
    let e = stderr_of(&run(&[]));
    assert!(e.contains("--force"), "{e}");
    // --levels adds the chain at 0 to 3 steps (here at the fluid's boundary): a 4x4 sheet
    let report = json_of(&run(&[
        "--levels",
        "--calibration",
        "boundary",
        "--force",
        "--json",
    ]));
    let sources: Vec<&str> = report["methods"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["source"].as_str().unwrap())
        .collect();
    assert_eq!(
        sources[11..],
        [
            "chain, 0 steps",
            "chain, 1 step",
            "chain, 2 steps",
            "chain, 3 steps"
        ],
        "{sources:?}"
    );
    let sheet = image::open(&out).unwrap();
    assert_eq!((sheet.width(), sheet.height()), (4 * 64, 4 * 48));
    let e = stderr_of(
        &bin()
            .args([
                "compare", "--scene", "column", "--size", "0x10", "--force", "--out",
            ])
            .arg(&out)
            .output()
            .unwrap(),
    );
    assert!(e.contains("between 1 and"), "{e}");
}

#[test]
fn render_background_is_flat_and_holes_are_reported() {
    let dir = ddb_dir();
    let d = dir.path();
    let out = d.join("white.png");
    let report = json_of(&render_ddb(
        d,
        &[
            "--background",
            "255,255,255",
            "--json",
            "--out",
            out.to_str().unwrap(),
        ],
    ));
    let img = image::open(&out).unwrap().to_rgba8();
    let white = fluid_surfels::quality::coverage_on(&img, [255, 255, 255]);
    let drawn = white.iter().filter(|&&c| c).count();
    // every pixel not drawn is exactly the background, and the report counts what is drawn
    assert_eq!(drawn as u64, report["covered_pixels"].as_u64().unwrap());
    assert!(img.get_pixel(0, 0).0 == [255, 255, 255, 255]);
    let h = fluid_surfels::quality::holes(&white, 64, 48, 3);
    assert_eq!(h.holes as u64, report["holes"]["holes"].as_u64().unwrap());
    assert!(
        report["holes_fraction"].as_f64().unwrap() < 0.05,
        "{report}"
    );
}

#[test]
fn render_up_z_turns_a_z_up_file_into_the_same_picture() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let set = ddb_set();
    fluid_surfels::io::write_particles(&d.join("ddb.vtk"), &set, None).unwrap();
    // the same water written by a z-up tool: y-up turned back by the inverse of --up z's turn
    let mut z_up = set.clone();
    z_up.rotate(fluid_surfels::view::UpAxis::Z.to_y_up().inverse());
    fluid_surfels::io::write_particles(&d.join("ddb_z.vtk"), &z_up, None).unwrap();
    let (a, b) = (d.join("y.png"), d.join("z.png"));
    succeeded(&render_ddb(d, &["--out", a.to_str().unwrap()]));
    succeeded(&render_input(
        &d.join("ddb_z.vtk"),
        &["--up", "z", "--out", b.to_str().unwrap()],
    ));
    let (a, b) = (
        image::open(&a).unwrap().to_rgba8(),
        image::open(&b).unwrap().to_rgba8(),
    );
    // the turn there and back costs float rounding only
    let diff = fluid_surfels::quality::mean_abs_diff(&a, &b);
    assert!(diff < 0.002, "mean abs diff {diff}");
    // without --up z the z-up file is seen lying on its side: a different picture
    let side = d.join("side.png");
    succeeded(&render_input(
        &d.join("ddb_z.vtk"),
        &["--out", side.to_str().unwrap()],
    ));
    let side = image::open(&side).unwrap().to_rgba8();
    assert!(fluid_surfels::quality::mean_abs_diff(&a, &side) > 0.01);
}

#[test]
fn render_sequence_resumes_with_skip_existing_and_the_first_frames_camera() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let set = ddb_set();
    // three frames: the water moves along x, so a camera fitted on another frame differs
    for f in 1..=3 {
        let mut s = set.clone();
        for p in &mut s.positions {
            p.x += 0.4 * (f - 1) as f32;
        }
        fluid_surfels::io::write_particles(&d.join(format!("f_{f}.vtk")), &s, None).unwrap();
    }
    let frames = d.join("frames");
    let seq = |extra: &[&str]| {
        bin()
            .args([
                "render",
                "--cpu",
                "--size",
                "48x40",
                "--source",
                "particles",
                "--frames",
                "1..=3",
                "--caustics-resolution",
                "32x32",
                "--input",
            ])
            .arg(d.join("f_{}.vtk"))
            .arg("--out")
            .arg(&frames)
            .args(extra)
            .output()
            .unwrap()
    };
    succeeded(&seq(&[]));
    let frame = |f: usize| frames.join(format!("frame_{f:04}.png"));
    let first: Vec<Vec<u8>> = (1..=3).map(|f| std::fs::read(frame(f)).unwrap()).collect();
    // refused without a flag: the message names both ways out
    let e = stderr_of(&seq(&[]));
    assert!(
        e.contains("--force") && e.contains("--skip-existing"),
        "{e}"
    );
    // interrupted after frame 1: frames 2 and 3 are rendered again, as the whole run drew them
    std::fs::remove_file(frame(2)).unwrap();
    std::fs::remove_file(frame(3)).unwrap();
    std::fs::write(frame(1), b"kept").unwrap();
    let resumed = seq(&["--skip-existing"]);
    succeeded(&resumed);
    assert!(String::from_utf8_lossy(&resumed.stdout).contains("skipping 1 of 3"));
    assert_eq!(std::fs::read(frame(1)).unwrap(), b"kept");
    for f in [2, 3] {
        assert_eq!(std::fs::read(frame(f)).unwrap(), first[f - 1], "frame {f}");
    }
    let none = seq(&["--skip-existing"]);
    succeeded(&none);
    assert!(String::from_utf8_lossy(&none.stdout).contains("nothing to do"));
}

#[test]
fn detect_writes_xyz_raw_with_out_format() {
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("surface.bin");
    let report = json_of(
        &bin()
            .args(["detect", "--json", "--out-format", "xyz-raw", "--input"])
            .arg(data("double_dam_break_frame_26_4732_particles.vtk"))
            .arg("--out")
            .arg(&raw)
            .output()
            .unwrap(),
    );
    let back =
        fluid_surfels::io::read_particles(&raw, Some(fluid_surfels::io::Format::XyzRaw)).unwrap();
    assert_eq!(
        back.len() as u64,
        report["counts"]["surface"].as_u64().unwrap(),
        "{report}"
    );
    assert_eq!(
        std::fs::metadata(&raw).unwrap().len(),
        12 * back.len() as u64
    );
}

/// Frame ranges and job counts: checked against the files before any work, nothing allocated
/// per frame of the range (issue 18).
#[test]
fn absurd_frame_ranges_and_job_counts_are_refused_at_once() {
    let dir = ddb_dir();
    std::fs::rename(dir.path().join("ddb.vtk"), dir.path().join("ddb_0.vtk")).unwrap();
    let pattern = dir.path().join("ddb_{}.vtk").display().to_string();
    for range in ["0..18446744073709551615", "0..1000000000", "0..=3"] {
        let out = bin()
            .args(["detect", "--input", &pattern, "--frames", range, "--out"])
            .arg(dir.path().join("out_{}.ply"))
            .output()
            .unwrap();
        let err = stderr_of(&out);
        assert!(
            err.contains("have no file") && err.contains("1, 2, 3") && err.contains("ddb_1.vtk"),
            "{range}: {err}"
        );
        assert!(
            !dir.path().join("out_0.ply").exists(),
            "no work before the check"
        );
    }
    let out = bin()
        .args(["info", &pattern, "--jobs", "1000000"])
        .output()
        .unwrap();
    assert!(stderr_of(&out).contains("1 to 1024"));
    let out = bin()
        .args(["detect", "--scene", "column", "--frame", "100000000"])
        .output()
        .unwrap();
    assert!(stderr_of(&out).contains("last frame"));
}

/// Work whose cost grows faster than its input is predicted and refused with the prediction
/// (issue 18): refinement steps, the low-pass radius.
#[test]
fn predicted_costs_over_the_limits_are_refused_with_the_figures() {
    let dir = ddb_dir();
    let input = dir.path().join("ddb.vtk");
    let out = bin()
        .args([
            "refine",
            "--steps",
            "8",
            "--memory-budget",
            "64M",
            "--input",
        ])
        .arg(&input)
        .output()
        .unwrap();
    let err = stderr_of(&out);
    assert!(
        err.contains("would make up to") && err.contains("memory budget of 64 MiB"),
        "{err}"
    );
    let out = bin()
        .args([
            "render",
            "--cpu",
            "--low-pass",
            "1e9",
            "--size",
            "800x600",
            "--input",
        ])
        .arg(&input)
        .arg("--out")
        .arg(dir.path().join("lp.png"))
        .output()
        .unwrap();
    let err = stderr_of(&out);
    assert!(
        err.contains("pixel fragments") && err.contains("--low-pass"),
        "{err}"
    );
    // an image whose buffers do not fit in what is left under a 3 GiB address-space limit
    let big = dir.path().join("big.png");
    let out = Command::new("sh")
        .arg("-c")
        .arg(format!(
            "ulimit -v 3000000 && exec '{}' render --cpu --size 8192x8192 --input '{}' --out '{}'",
            env!("CARGO_BIN_EXE_fluid-surfels"),
            input.display(),
            big.display()
        ))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1), "an error exit, not an abort");
    let err = stderr_of(&out);
    assert!(err.contains("8192x8192 render needs 5120 MiB"), "{err}");
    // negative values reach the range checks, which say what is allowed
    let neg = dir.path().join("neg.png").display().to_string();
    let out = render_ddb(dir.path(), &["--low-pass", "-2", "--out", &neg]);
    assert!(stderr_of(&out).contains("must be finite and >= 0"));
    let out = bin()
        .args(["detect", "--radius", "-1", "--input"])
        .arg(&input)
        .output()
        .unwrap();
    assert!(stderr_of(&out).contains("must be finite and > 0, got -1"));
    // a NaN radius is named as the radius, not as the grid's box
    let out = bin()
        .args(["surfels", "--radius", "nan", "--input"])
        .arg(&input)
        .arg("--out")
        .arg(dir.path().join("s.ply"))
        .output()
        .unwrap();
    let err = stderr_of(&out);
    assert!(err.contains("radius") && !err.contains("box"), "{err}");
}

/// One particle leaked a billion units away: the error says `--bounds` exists, and with it the
/// file works and the report counts what was dropped (issue 18).
#[test]
fn bounds_drop_leaked_particles_and_are_suggested() {
    let dir = tempfile::tempdir().unwrap();
    let mut set = ddb_set();
    set.positions.push(glam::Vec3::new(1e9, 0.0, 0.0));
    let set = fluid_surfels::ParticleSet::from_positions(set.positions);
    let leak = dir.path().join("leak.ply");
    fluid_surfels::io::write_particles(&leak, &set, None).unwrap();
    let out = bin()
        .args(["detect", "--input"])
        .arg(&leak)
        .output()
        .unwrap();
    let err = stderr_of(&out);
    assert!(err.contains("--bounds"), "{err}");
    let out = bin()
        .args(["detect", "--json", "--bounds", "-2,-1,-2,2,2,2", "--input"])
        .arg(&leak)
        .output()
        .unwrap();
    let report = json_of(&out);
    assert_eq!(report["outside_bounds"], 1);
    assert_eq!(report["particles"], 4732);
    let out = bin()
        .args(["detect", "--bounds", "1,0,0,0,1,1", "--input"])
        .arg(&leak)
        .output()
        .unwrap();
    assert!(stderr_of(&out).contains("min <= its max"));
}

/// Surfels read from a file: a huge radius is named as the radius, zero and negative radii
/// are skipped with a count (issue 18).
#[test]
fn surfel_files_with_bad_radii_are_named_or_counted() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, radii: Vec<f64>| {
        let n = radii.len();
        let mut set = fluid_surfels::ParticleSet::from_positions(
            (0..n)
                .map(|i| glam::Vec3::new((i % 10) as f32 * 0.1, (i / 10) as f32 * 0.1, 0.0))
                .collect(),
        );
        set.normals = Some(vec![glam::Vec3::Z; n]);
        set.extra.push(fluid_surfels::Attribute::scalar(
            "radius",
            fluid_surfels::ScalarKind::F32,
            radii,
        ));
        let path = dir.path().join(name);
        fluid_surfels::io::write_particles(&path, &set, None).unwrap();
        path
    };
    let mut radii = vec![0.08; 100];
    radii[17] = 1e30;
    let huge = write("huge.ply", radii);
    let out = bin()
        .args(["render", "--cpu", "--size", "64x48", "--surfels"])
        .arg(&huge)
        .arg("--out")
        .arg(dir.path().join("h.png"))
        .output()
        .unwrap();
    let err = stderr_of(&out);
    assert!(
        err.contains("surfel 17 has radius") && !err.contains("camera"),
        "{err}"
    );
    let mut radii = vec![0.08; 100];
    for r in &mut radii[..7] {
        *r = 0.0;
    }
    radii[50] = -1.0;
    let zero = write("zero.ply", radii);
    let out = bin()
        .args(["render", "--cpu", "--size", "64x48", "--surfels"])
        .arg(&zero)
        .arg("--out")
        .arg(dir.path().join("z.png"))
        .output()
        .unwrap();
    succeeded(&out);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("warning: 8 of 100 surfels cannot be drawn"),
        "{text}"
    );
}

/// A file that inflates beyond the memory budget is refused by a process whose address space
/// is limited below what inflating would take, with the budget named instead of an abort
/// (issue 18).
#[test]
fn a_zlib_bomb_is_refused_under_a_lowered_address_space_limit() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    // one compressed MiB of zeros repeated 1200 times: 1.2 GiB declared, 1.2 MB on disk
    let mib = vec![0u8; 1 << 20];
    let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
    e.write_all(&mib).unwrap();
    let block = e.finish().unwrap();
    let copies = 1200u32;
    let points = u64::from(copies) * (1 << 20) / 12;
    let mut file = format!("<VTKFile type=\"UnstructuredGrid\" compressor=\"vtkZLibDataCompressor\" header_type=\"UInt32\"><UnstructuredGrid><Piece NumberOfPoints=\"{points}\"><Points><DataArray type=\"Float32\" NumberOfComponents=\"3\" format=\"appended\" offset=\"0\"/></Points></Piece></UnstructuredGrid><AppendedData encoding=\"raw\">_").into_bytes();
    for v in [copies, 1 << 20, 0] {
        file.extend_from_slice(&v.to_le_bytes());
    }
    for _ in 0..copies {
        file.extend_from_slice(&(block.len() as u32).to_le_bytes());
    }
    for _ in 0..copies {
        file.extend_from_slice(&block);
    }
    file.extend_from_slice(b"</AppendedData></VTKFile>");
    let bomb = dir.path().join("bomb.vtu");
    std::fs::write(&bomb, &file).unwrap();
    let limited = |kib: u64, file: &Path| {
        Command::new("sh")
            .arg("-c")
            .arg(format!(
                "ulimit -v {kib} && exec '{}' info '{}'",
                env!("CARGO_BIN_EXE_fluid-surfels"),
                file.display()
            ))
            .output()
            .unwrap()
    };
    // a header claiming 4 GiB from a few compressed bytes: refused from the header alone
    let mut liar = b"<VTKFile type=\"UnstructuredGrid\" compressor=\"vtkZLibDataCompressor\" header_type=\"UInt32\"><UnstructuredGrid><Piece NumberOfPoints=\"8\"><Points><DataArray type=\"Float32\" NumberOfComponents=\"3\" format=\"appended\" offset=\"0\"/></Points></Piece></UnstructuredGrid><AppendedData encoding=\"raw\">_".to_vec();
    for v in [1u32, u32::MAX, u32::MAX, 10] {
        liar.extend_from_slice(&v.to_le_bytes());
    }
    liar.extend_from_slice(&[0x78, 0x9c, 3, 0, 0, 0, 0, 1, 0, 0]);
    liar.extend_from_slice(b"</AppendedData></VTKFile>");
    let liar_path = dir.path().join("liar.vtu");
    std::fs::write(&liar_path, &liar).unwrap();
    let out = limited(1_500_000, &liar_path);
    assert_eq!(out.status.code(), Some(1), "an error exit, not an abort");
    let err = stderr_of(&out);
    assert!(err.contains("inflates 1032x at most"), "{err}");
    // 1.5 GiB of address space, less than the points need: the limit is what is available
    let out = limited(1_500_000, &bomb);
    assert_eq!(out.status.code(), Some(1), "an error exit, not an abort");
    let err = stderr_of(&out);
    assert!(err.contains("bytes of memory available"), "{err}");
    // 8 GiB: the points fit, but inflating 1.2 GiB is over the 1 GiB budget
    let out = limited(8 << 20, &bomb);
    assert_eq!(out.status.code(), Some(1), "an error exit, not an abort");
    let err = stderr_of(&out);
    assert!(err.contains("memory budget of 1073741824"), "{err}");
    assert!(!err.contains("memory allocation"), "{err}");
}

/// `--up` on the stage commands turns their pictures, not the points they write (issue 14).
#[test]
fn stage_pictures_take_up_and_written_points_keep_the_files_axes() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let set = ddb_set();
    let mut z_up = set.clone();
    z_up.rotate(fluid_surfels::view::UpAxis::Z.to_y_up().inverse());
    fluid_surfels::io::write_particles(&d.join("y.vtk"), &set, None).unwrap();
    fluid_surfels::io::write_particles(&d.join("z.vtk"), &z_up, None).unwrap();
    let run = |cmd: &str, input: &str, up: &str, tag: &str| {
        let png = d.join(format!("{cmd}_{tag}.png"));
        let out = d.join(format!("{cmd}_{tag}.ply"));
        succeeded(
            &bin()
                .args([cmd, "--input"])
                .arg(d.join(input))
                .args(["--up", up, "--radius", "0.14", "--png"])
                .arg(&png)
                .arg("--out")
                .arg(&out)
                .output()
                .unwrap(),
        );
        (
            image::open(&png).unwrap().to_rgba8(),
            fluid_surfels::io::read_particles(&out, None).unwrap(),
        )
    };
    for cmd in ["detect", "refine", "surfels"] {
        let (a, pa) = run(cmd, "y.vtk", "y", "y");
        let (b, pb) = run(cmd, "z.vtk", "z", "z");
        let (side, _) = run(cmd, "z.vtk", "y", "side");
        let same = fluid_surfels::quality::mean_abs_diff(&a, &b);
        let other = fluid_surfels::quality::mean_abs_diff(&a, &side);
        println!("{cmd}: mean abs diff {same} turned, {other} on its side");
        assert!(
            same < 0.01 && other > 2.0 * same,
            "{cmd}: {same} against {other}"
        );
        // the written points are in the file's own axes: the z-up file's stay z-up
        let span = |s: &fluid_surfels::ParticleSet| {
            let (lo, hi) = s.bounds().unwrap();
            hi - lo
        };
        let (ya, zb) = (span(&pa), span(&pb));
        assert!(
            (ya.y - zb.z).abs() < 0.05 * ya.y.max(1e-3),
            "{cmd}: y extent {} written as z extent {}",
            ya.y,
            zb.z
        );
    }
}

/// `render --frames --fit union` fits the sequence's camera and pool to every frame's
/// particles; the column scene, whose frames are simulated, refuses it (issue 14).
#[test]
fn render_sequence_fits_the_union_of_the_frames() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let set = ddb_set();
    let mut moved = set.clone();
    for p in &mut moved.positions {
        p.x += 2.0;
    }
    fluid_surfels::io::write_particles(&d.join("f_0.vtk"), &set, None).unwrap();
    fluid_surfels::io::write_particles(&d.join("f_1.vtk"), &moved, None).unwrap();
    let render = |fit: &str| {
        let out = d.join(fit);
        let run = bin()
            .args([
                "render", "--cpu", "--size", "96x72", "--frames", "0..=1", "--fit", fit,
            ])
            .arg("--input")
            .arg(d.join("f_{}.vtk"))
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        succeeded(&run);
        image::open(out.join("frame_0001.png")).unwrap().to_rgba8()
    };
    let (first, union) = (render("first"), render("union"));
    assert!(fluid_surfels::quality::mean_abs_diff(&first, &union) > 0.01);
    let out = bin()
        .args([
            "render", "--cpu", "--scene", "column", "--frames", "0..2", "--fit", "union",
        ])
        .arg("--out")
        .arg(d.join("col"))
        .output()
        .unwrap();
    assert!(stderr_of(&out).contains("needs an --input pattern"));
}

/// `render --save-surfels` writes the surfels it renders: read back with `--surfels` and drawn
/// from the same camera they give the same image, for the shaded splats and the finished frame;
/// with `--frames` it is refused, and an existing file is kept without `--force`.
#[test]
fn render_saves_the_surfels_it_draws() {
    let dir = ddb_dir();
    let saved = dir.path().join("surfels.ply");
    let first = dir.path().join("first.png");
    let out = render_ddb(
        dir.path(),
        &[
            "--save-surfels",
            saved.to_str().unwrap(),
            "--out",
            first.to_str().unwrap(),
            "--json",
        ],
    );
    let report = json_of(&out);
    let set = fluid_surfels::io::read_particles(&saved, None).unwrap();
    assert_eq!(
        set.len() as u64,
        report["surfels"].as_u64().unwrap(),
        "every rendered surfel is written"
    );
    assert!(set.normals.is_some() && set.attribute("radius").is_some());
    // drawn again from the file, with the first run's camera
    let c = &report["camera"];
    let camera: Vec<String> = ["eye", "target"]
        .iter()
        .flat_map(|k| c[k].as_array().unwrap().clone())
        .map(|v| v.as_f64().unwrap().to_string())
        .chain([c["fov_y_degrees"].as_f64().unwrap().to_string()])
        .collect();
    let again = dir.path().join("again.png");
    let out = bin()
        .args(["render", "--cpu", "--size", "64x48", "--surfels"])
        .arg(&saved)
        .args(["--camera", &camera.join(","), "--out"])
        .arg(&again)
        .output()
        .unwrap();
    succeeded(&out);
    let (a, b) = (
        image::open(&first).unwrap().to_rgba8(),
        image::open(&again).unwrap().to_rgba8(),
    );
    let diff = fluid_surfels::quality::mean_abs_diff(&a, &b);
    assert!(diff < 1e-3, "mean absolute difference {diff}");
    // the finished frame's surfels too
    let frame_surfels = dir.path().join("frame_surfels.vtk");
    let out = render_ddb(
        dir.path(),
        &[
            "--optics",
            "--save-surfels",
            frame_surfels.to_str().unwrap(),
            "--out",
            dir.path().join("frame.png").to_str().unwrap(),
        ],
    );
    succeeded(&out);
    let frame_set = fluid_surfels::io::read_particles(&frame_surfels, None).unwrap();
    assert_eq!(frame_set.positions, set.positions);
    // an existing file is kept without --force; not with --frames
    let before = std::fs::read(&saved).unwrap();
    let out = render_ddb(
        dir.path(),
        &[
            "--save-surfels",
            saved.to_str().unwrap(),
            "--out",
            dir.path().join("third.png").to_str().unwrap(),
        ],
    );
    assert!(stderr_of(&out).contains("surfels.ply"));
    assert_eq!(std::fs::read(&saved).unwrap(), before);
    let out = bin()
        .args([
            "render",
            "--scene",
            "column",
            "--frames",
            "0..2",
            "--save-surfels",
        ])
        .arg(&saved)
        .arg("--out")
        .arg(dir.path().join("seq"))
        .output()
        .unwrap();
    assert!(stderr_of(&out).contains("--save-surfels"));
}

/// `render` prints a support radius far off on stderr as soon as it is known, before the work
/// that follows: here before a splatting its fragment limit refuses.
#[test]
fn render_warns_of_an_absurd_radius_before_the_work() {
    let dir = ddb_dir();
    let out = render_ddb(
        dir.path(),
        &[
            "--radius",
            "0.5",
            "--max-fragments",
            "1",
            "--out",
            dir.path().join("r.png").to_str().unwrap(),
        ],
    );
    let stderr = stderr_of(&out);
    let warning = stderr
        .find("warning: support radius 0.5 gives")
        .unwrap_or_else(|| panic!("{stderr}"));
    let error = stderr.find("error:").unwrap_or_else(|| panic!("{stderr}"));
    assert!(warning < error, "{stderr}");
    assert!(stderr.contains("too large"), "{stderr}");
}

/// `render --renderer ssfr`: every `--filter` draws the library's screen-space image of the
/// particles from the report's camera, `--no-narrow-band` draws every particle, the finished
/// frame runs through it, and `--gpu` draws the CPU's pictures (shaded and finished).
#[test]
fn render_draws_the_screen_space_surface_with_each_filter() {
    use fluid_surfels::ssfr::{DepthFilter, ScreenSpace, SsfrParams};
    let dir = ddb_dir();
    let d = dir.path();
    let set = ddb_set();
    let h = fluid_surfels::neighbours::support_radius(&set.positions).unwrap();
    let radii = vec![h; set.len()];
    for filter in DepthFilter::ALL {
        for band in [true, false] {
            let out = d.join(format!("ssfr-{filter}-{band}.png"));
            let mut args = vec![
                "--renderer",
                "ssfr",
                "--filter",
                filter.as_str(),
                "--json",
                "--out",
                out.to_str().unwrap(),
            ];
            if !band {
                args.push("--no-narrow-band");
            }
            let report = json_of(&render_ddb(d, &args));
            assert_eq!(report["renderer"], "ssfr", "{report}");
            assert_eq!(report["backend"], "cpu reference", "{report}");
            let camera: fluid_surfels::splat::Camera =
                serde_json::from_value(report["camera"].clone()).unwrap();
            let params = SsfrParams {
                filter,
                narrow_band: band,
                ..Default::default()
            };
            let v = fluid_surfels::splat::View::new(
                &camera,
                &fluid_surfels::splat::Light::default(),
                &fluid_surfels::splat::SplatParams::default(),
                64,
                48,
            )
            .unwrap();
            let expected = ScreenSpace::new(&set.positions, &radii, h, &params)
                .unwrap()
                .render_view(&v)
                .unwrap();
            assert!(expected.render.covered_pixels() > 200);
            let png = image::open(&out).unwrap().to_rgba8();
            assert_eq!(png, expected.render.image, "{filter}, band {band}");
        }
    }
    let finished = render_ddb(
        d,
        &[
            "--renderer",
            "ssfr",
            "--optics",
            "--out",
            d.join("ssfr-frame.png").to_str().unwrap(),
        ],
    );
    succeeded(&finished);
    // the shaded splats on the GPU: the CPU's picture
    if fluid_surfels::gpu::context_or_skip("render --renderer ssfr --gpu")
        .unwrap()
        .is_some()
    {
        let psnr = gpu_against_cpu(d, "ssfr", false);
        assert!(psnr >= 40.0, "GPU against CPU screen space {psnr:.1} dB");
        // and the finished frame through GpuPipeline
        let psnr = gpu_against_cpu(d, "ssfr", true);
        assert!(
            psnr >= 35.0,
            "GPU against CPU screen-space frame {psnr:.1} dB"
        );
    }
}

/// `bench ssfr` at a small size: each filter with and without the narrow band, the band's
/// share, and the band's image against every particle's.
#[test]
fn bench_ssfr_times_each_filter_with_and_without_the_band() {
    let v = json_of(
        &bin()
            .args(["bench", "ssfr", "--size", "96x64", "--repeat", "1"])
            .args(["--filters", "plane,curvature-flow", "--json", "--input"])
            .arg(data("dam_break_frame_23_24389_particles.bgeo"))
            .output()
            .unwrap(),
    );
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 4, "{v}");
    let particles = v["particles"].as_u64().unwrap();
    assert_eq!(particles, 24_389);
    let band = v["band"].as_u64().unwrap();
    assert!(band > 0 && band < particles, "{v}");
    assert!(v["memory_saved"].as_f64().unwrap() > 0.0, "{v}");
    for r in rows {
        assert!(r["median_ms"].as_f64().unwrap() > 0.0, "{r}");
        assert!(r["covered_pixels"].as_u64().unwrap() > 100, "{r}");
        if r["narrow_band"].as_bool().unwrap() {
            assert_eq!(r["drawn"].as_u64().unwrap(), band, "{r}");
            assert!(r["psnr_against_all_db"].as_f64().unwrap() >= 35.0, "{r}");
        } else {
            assert_eq!(r["drawn"].as_u64().unwrap(), particles, "{r}");
        }
    }
}

/// `detect --method lnm` on the dam break: the written surface is the narrow band (every
/// band particle, each with a unit normal), the report holds its agreement with the
/// centre-of-mass classes of the same frame (every centre-of-mass surface particle in the band
/// here), and a sequence reports the agreement per frame.
#[test]
fn detect_with_the_lnm_method_writes_the_band_and_its_agreement() {
    let dir = tempfile::tempdir().unwrap();
    let input = data("dam_break_frame_23_24389_particles.bgeo");
    let out = dir.path().join("band.ply");
    let v = json_of(
        &bin()
            .args([
                "detect", "--method", "lnm", "--json", "--input", &input, "--out",
            ])
            .arg(&out)
            .output()
            .unwrap(),
    );
    let a = &v["lnm"]["agreement"];
    let band = a["band"].as_u64().unwrap();
    assert!(band > 10_000 && band < 24_389, "{v}");
    assert_eq!(a["detected_only"], 0, "{v}");
    assert_eq!(a["recall"].as_f64().unwrap(), 1.0, "{v}");
    let counts = &v["counts"];
    assert_eq!(
        counts["surface"].as_u64().unwrap() + counts["isolated"].as_u64().unwrap(),
        band,
        "{v}"
    );
    let written = fluid_surfels::io::read_particles(&out, None).unwrap();
    let isolated = counts["isolated"].as_u64().unwrap() as usize;
    assert_eq!(written.len() + isolated, band as usize);
    for n in written.normals.as_ref().unwrap() {
        assert!((n.length() - 1.0).abs() < 1e-4, "{n}");
    }
    // without it: no lnm entry
    let v = json_of(
        &bin()
            .args(["detect", "--json", "--input", &input])
            .output()
            .unwrap(),
    );
    assert!(v.get("lnm").is_none(), "{v}");
    // a sequence of two copies
    for f in 0..2 {
        std::fs::copy(&input, dir.path().join(format!("f{f}.bgeo"))).unwrap();
    }
    let pattern = dir.path().join("f{}.bgeo");
    let v = json_of(
        &bin()
            .args([
                "detect", "--method", "lnm", "--json", "--frames", "0..=1", "--input",
            ])
            .arg(&pattern)
            .output()
            .unwrap(),
    );
    let frames = v["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 2, "{v}");
    for f in frames {
        assert_eq!(f["lnm"]["band"].as_u64().unwrap(), band, "{f}");
    }
}

/// Every command the README and the pages of `docs/` show (the `fluid-surfels ...` lines of
/// their `sh` blocks) names a subcommand that exists and only options that its `--help` lists,
/// so the docs stay true as options change.
#[test]
fn documented_commands_exist() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut pages = vec![root.join("README.md")];
    let mut docs: Vec<_> = std::fs::read_dir(root.join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    docs.sort();
    pages.extend(docs);
    let mut helps = std::collections::HashMap::new();
    let mut checked = 0;
    for page in &pages {
        let text = std::fs::read_to_string(page).unwrap();
        let mut in_sh = false;
        let mut command = String::new();
        for line in text.lines() {
            if line.starts_with("```") {
                in_sh = line == "```sh";
                continue;
            }
            if !in_sh {
                continue;
            }
            // a command continued over lines with a trailing backslash
            command.push_str(line.trim_end_matches('\\'));
            command.push(' ');
            if line.ends_with('\\') {
                continue;
            }
            let full = std::mem::take(&mut command);
            let code = full.split(" #").next().unwrap_or("").trim();
            let Some(rest) = code.strip_prefix("fluid-surfels") else {
                continue;
            };
            let words: Vec<&str> = rest.split_whitespace().collect();
            let mut sub: Vec<&str> = Vec::new();
            if let Some(&first) = words.first().filter(|w| !w.starts_with('-')) {
                sub.push(first);
                if first == "bench" {
                    sub.push(words[1]);
                }
            }
            let help = helps.entry(sub.join(" ")).or_insert_with(|| {
                let out = bin().args(&sub).arg("--help").output().unwrap();
                assert!(
                    out.status.success(),
                    "{}: `fluid-surfels {}` is not a command",
                    page.display(),
                    sub.join(" ")
                );
                String::from_utf8_lossy(&out.stdout).into_owned()
            });
            for word in &words {
                let flag = word.split(['=', '[', ']']).next().unwrap_or("");
                if !flag.starts_with("--") || flag.len() < 3 {
                    continue;
                }
                let listed = help.match_indices(flag).any(|(i, _)| {
                    !help[i + flag.len()..]
                        .starts_with(|c: char| c.is_ascii_alphanumeric() || c == '-')
                });
                assert!(
                    listed,
                    "{}: `fluid-surfels {}` has no option {flag} (in `{code}`)",
                    page.display(),
                    sub.join(" ")
                );
                checked += 1;
            }
        }
    }
    assert!(checked > 50, "only {checked} options found in the docs");
}

/// `render --detail auto|fixed` (auto by default): a small picture takes fewer steps, reported in
/// `--json`'s `detail`; `--level-map` draws the refined points coloured by their level at the
/// picture's size; `--save-surfels` files are `fixed` unless `--detail` says otherwise.
#[test]
fn render_chooses_the_detail_from_the_view() {
    let dir = ddb_dir();
    let map = dir.path().join("levels.png");
    let render_ddb = |dir: &Path, extra: &[&str]| {
        bin()
            .args(["render", "--cpu", "--force", "--size", "64x48", "--out"])
            .arg(dir.join("chain.png"))
            .arg("--input")
            .arg(dir.join("ddb.vtk"))
            .args(extra)
            .output()
            .unwrap()
    };
    let auto = json_of(&render_ddb(
        dir.path(),
        &["--level-map", map.to_str().unwrap(), "--json"],
    ));
    let fixed = json_of(&render_ddb(dir.path(), &["--detail", "fixed", "--json"]));
    let saving = json_of(&render_ddb(
        dir.path(),
        &[
            "--save-surfels",
            dir.path().join("s.ply").to_str().unwrap(),
            "--json",
        ],
    ));
    let (a, f, s) = (&auto["detail"], &fixed["detail"], &saving["detail"]);
    assert_eq!(a["detail"], "auto");
    assert_eq!(f["detail"], "fixed");
    assert_eq!(s["detail"], "fixed");
    assert_eq!(f["steps"], 3);
    assert!(a["steps"].as_u64().unwrap() < 3, "{a}");
    assert!(a["refined_points"].as_u64().unwrap() < f["refined_points"].as_u64().unwrap());
    let levels = image::open(&map).unwrap().to_rgb8();
    assert_eq!(levels.dimensions(), (64, 48));
    // some pixels in the colour of the level it took
    let level = a["steps"].as_u64().unwrap() as usize;
    let colour = fluid_surfels::preview::palette::STEPS[level];
    // shaded: the colour times a shade in [0.35, 1]
    let of_level = |c: [u8; 3]| {
        let peak = f32::from(*colour.iter().max().unwrap());
        let shade = f32::from(*c.iter().max().unwrap()) / peak;
        c != fluid_surfels::preview::palette::LIGHT_BACKGROUND
            && (0..3).all(|k| (f32::from(c[k]) - shade * f32::from(colour[k])).abs() <= 12.0)
    };
    assert!(
        levels.pixels().any(|p| of_level(p.0)),
        "no point of level {level} drawn"
    );
    let out = bin()
        .args(["render", "--optics", "--level-map", "x.png", "--input"])
        .arg(dir.path().join("ddb.vtk"))
        .output()
        .unwrap();
    assert!(!out.status.success());
}

/// A standard output closed before the command writes (`fluid-surfels info F | head -0`) ends
/// it quietly: no panic message ("failed printing to stdout: Broken pipe").
#[test]
fn a_closed_stdout_ends_quietly() {
    let dir = ddb_dir();
    let mut child = bin()
        .args(["info"])
        .arg(dir.path().join("ddb.vtk"))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
}

/// `render --frames --shard K/N` (issue 39): a 24-frame column sequence written to files and
/// rendered in three shards (sharing one `--plan` file, each warming up on the frames before
/// its chunk) gives the serial run's PNGs byte for byte; bad shards are refused at once.
#[test]
fn render_shards_draw_the_serial_frames_and_refuse_bad_shards() {
    use fluid_surfels::scenes::{ColumnParams, ColumnSim};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut sim = ColumnSim::new(ColumnParams::default()).unwrap();
    for f in 0..24 {
        sim.advance_to(f);
        fluid_surfels::io::write_particles(&d.join(format!("c_{f}.vtk")), sim.particles(), None)
            .unwrap();
    }
    let render = |out: &str, extra: &[&str]| {
        bin()
            .args([
                "render",
                "--cpu",
                "--size",
                "48x36",
                "--caustics-resolution",
                "32x32",
                "--frames",
                "0..24",
                "--input",
            ])
            .arg(d.join("c_{}.vtk"))
            .arg("--out")
            .arg(d.join(out))
            .args(extra)
            .output()
            .unwrap()
    };
    succeeded(&render("serial", &[]));
    let plan = d.join("plan.json");
    let plan = plan.to_str().unwrap();
    for k in 1..=3 {
        let shard = format!("{k}/3");
        let out = render("sharded", &["--shard", &shard, "--plan", plan]);
        succeeded(&out);
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(text.contains(&format!("shard {k}/3")), "{text}");
    }
    assert!(d.join("plan.json").exists());
    for f in 0..24 {
        let name = format!("frame_{f:04}.png");
        let serial = std::fs::read(d.join("serial").join(&name)).unwrap();
        let sharded = std::fs::read(d.join("sharded").join(&name)).unwrap();
        assert!(serial == sharded, "frame {f} differs");
    }
    // detection over the same files: three shards, and three jobs, write the serial run's
    // classes (each job and shard warmed up on the 8 frames before its first)
    let detect = |out: &str, extra: &[&str]| {
        let out = d.join(out).join("s_{}.ply");
        bin()
            .args(["detect", "--frames", "0..24", "--input"])
            .arg(d.join("c_{}.vtk"))
            .arg("--out")
            .arg(&out)
            .args(extra)
            .output()
            .unwrap()
    };
    for folder in ["d_serial", "d_shards", "d_jobs"] {
        std::fs::create_dir(d.join(folder)).unwrap();
    }
    succeeded(&detect("d_serial", &[]));
    for k in 1..=3 {
        succeeded(&detect("d_shards", &["--shard", &format!("{k}/3")]));
    }
    succeeded(&detect("d_jobs", &["--jobs", "3"]));
    for f in 0..24 {
        let name = format!("s_{f}.ply");
        let serial = std::fs::read(d.join("d_serial").join(&name)).unwrap();
        for other in ["d_shards", "d_jobs"] {
            let o = std::fs::read(d.join(other).join(&name)).unwrap();
            assert!(serial == o, "{other}: frame {f}'s classes differ");
        }
    }
    // bad shards: clear errors before any work
    for (shard, env, what) in [
        ("3/2", None, "1 <= K <= N"),
        ("0/3", None, "1 <= K <= N"),
        ("x", None, "expected K/N"),
        ("slurm", None, "SLURM_ARRAY_TASK_ID is not set"),
        ("slurm", Some(("7", "1", "3")), "not among"),
        ("slurm", Some(("a", "1", "3")), "not a whole number"),
    ] {
        let mut cmd = render("bad", &["--shard", shard]);
        if let Some((id, min, count)) = env {
            cmd = bin()
                .args(["render", "--cpu", "--frames", "0..24", "--shard", "slurm"])
                .arg("--input")
                .arg(d.join("c_{}.vtk"))
                .arg("--out")
                .arg(d.join("bad"))
                .env("SLURM_ARRAY_TASK_ID", id)
                .env("SLURM_ARRAY_TASK_MIN", min)
                .env("SLURM_ARRAY_TASK_COUNT", count)
                .output()
                .unwrap();
        }
        assert!(!cmd.status.success(), "{shard} {env:?}");
        let e = stderr_of(&cmd);
        assert!(e.contains(what), "{shard} {env:?}: {e}");
        assert!(!e.contains("panicked"), "{e}");
        assert!(!d.join("bad").exists(), "{shard}: work was done");
    }
}

/// `--threads N` (every command) caps the threads of the work: a bench reports the pool it ran
/// in; 0 and absurd counts are refused.
#[test]
fn threads_cap_every_command() {
    let v = json_of(
        &bin()
            .args([
                "bench",
                "lnm",
                "--particles",
                "5000",
                "--repeat",
                "1",
                "--json",
            ])
            .args(["--threads", "1"])
            .output()
            .unwrap(),
    );
    assert_eq!(v["threads"].as_u64(), Some(1), "{v}");
    for bad in ["0", "5000", "x"] {
        let out = bin()
            .args(["info", &data("cube.ply"), "--threads", bad])
            .output()
            .unwrap();
        assert!(!out.status.success(), "--threads {bad}");
        assert!(
            stderr_of(&out).contains("threads from 1 to"),
            "{}",
            stderr_of(&out)
        );
    }
}

/// `mesh` (issue 40, first part): a closed mesh of a real file, its PLY read back by our own
/// reader (the vertices), its OBJ counted; a sequence of column frames with --skip-existing
/// writes only the missing frames; an unknown mesh format is refused before any work.
#[test]
fn mesh_writes_closed_meshes_of_files_and_sequences() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let input = data("double_dam_break_frame_26_4732_particles.vtk");
    let ply = d.join("ddb.ply");
    let v = json_of(
        &bin()
            .args(["mesh", "--input", &input, "--json", "--out"])
            .arg(&ply)
            .output()
            .unwrap(),
    );
    assert_eq!(v["closed"], true, "{v}");
    let vertices = v["vertices"].as_u64().unwrap() as usize;
    assert!(
        vertices > 10_000 && v["triangles"].as_u64().unwrap() as usize > vertices,
        "{v}"
    );
    let back = fluid_surfels::io::read_particles(&ply, None).unwrap();
    assert_eq!(back.len(), vertices);
    let obj = d.join("ddb.obj");
    succeeded(
        &bin()
            .args(["mesh", "--input", &input, "--out"])
            .arg(&obj)
            .output()
            .unwrap(),
    );
    let text = std::fs::read_to_string(&obj).unwrap();
    assert_eq!(
        text.lines().filter(|l| l.starts_with("v ")).count(),
        vertices
    );
    // a sequence: three column frames, one kept
    let mut sim = fluid_surfels::scenes::ColumnSim::new(Default::default()).unwrap();
    for f in 0..3 {
        sim.advance_to(f);
        fluid_surfels::io::write_particles(&d.join(format!("c_{f}.vtk")), sim.particles(), None)
            .unwrap();
    }
    std::fs::write(d.join("m_1.ply"), b"kept").unwrap();
    let out = bin()
        .args(["mesh", "--frames", "0..3", "--skip-existing", "--input"])
        .arg(d.join("c_{}.vtk"))
        .arg("--out")
        .arg(d.join("m_{}.ply"))
        .output()
        .unwrap();
    succeeded(&out);
    assert!(String::from_utf8_lossy(&out.stdout).contains("2 frames meshed, 1 skipped"));
    assert_eq!(std::fs::read(d.join("m_1.ply")).unwrap(), b"kept");
    // the column's frames have velocities: the meshes carry them, read back with the faces
    for f in [0, 2] {
        let m = fluid_surfels::mesh::Mesh::read(&d.join(format!("m_{f}.ply"))).unwrap();
        assert!(m.positions.len() > 1000, "frame {f}");
        assert!(m.is_closed(), "frame {f}");
        let v = m.velocities.as_ref().expect("velocities");
        assert_eq!(v.len(), m.positions.len());
        assert!(v.iter().all(|v| v.is_finite()), "frame {f}");
    }
    // resumed frames equal a run straight through (the skipped frame still runs detection, so
    // the classes' hysteresis is the same)
    succeeded(
        &bin()
            .args(["mesh", "--frames", "0..3", "--input"])
            .arg(d.join("c_{}.vtk"))
            .arg("--out")
            .arg(d.join("s_{}.ply"))
            .output()
            .unwrap(),
    );
    for f in [0, 2] {
        assert_eq!(
            std::fs::read(d.join(format!("m_{f}.ply"))).unwrap(),
            std::fs::read(d.join(format!("s_{f}.ply"))).unwrap(),
            "frame {f}"
        );
    }
    // the same as legacy VTK, read back equal to the PLY
    let vtk = d.join("m_0.vtk");
    succeeded(
        &bin()
            .args(["mesh", "--input"])
            .arg(d.join("c_0.vtk"))
            .arg("--out")
            .arg(&vtk)
            .output()
            .unwrap(),
    );
    assert_eq!(
        fluid_surfels::mesh::Mesh::read(&vtk).unwrap(),
        fluid_surfels::mesh::Mesh::read(&d.join("m_0.ply")).unwrap()
    );
    // an unknown format: refused at once, nothing written
    let bad = bin()
        .args(["mesh", "--input", &input, "--out"])
        .arg(d.join("m.stl"))
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(
        stderr_of(&bad)
            .contains(".ply (binary), .obj, .vtk (legacy POLYDATA), .vtu (VTK XML) or .usda"),
        "{}",
        stderr_of(&bad)
    );
    assert!(!d.join("m.stl").exists());
}

/// `mesh` to USD: a `.usda` frame per frame (time samples at its number) and a stage that
/// plays them (value clips over every frame of --frames), written once more unchanged by a
/// resumed run or another shard, refused over a different file; --stage names it.
#[test]
fn mesh_writes_a_usd_sequence_and_its_stage() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut sim = fluid_surfels::scenes::ColumnSim::new(Default::default()).unwrap();
    for f in 0..2 {
        sim.advance_to(f);
        fluid_surfels::io::write_particles(&d.join(format!("c_{f}.vtk")), sim.particles(), None)
            .unwrap();
    }
    let run = |extra: &[&str]| {
        bin()
            .args(["mesh", "--frames", "0..2", "--input"])
            .arg(d.join("c_{}.vtk"))
            .arg("--out")
            .arg(d.join("mesh_{:03}.usda"))
            .args(extra)
            .output()
            .unwrap()
    };
    let out = run(&[]);
    succeeded(&out);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("wrote the USD stage"), "{stdout}");
    let stage = std::fs::read_to_string(d.join("mesh.usda")).unwrap();
    assert!(
        stage.contains("asset[] assetPaths = [@./mesh_000.usda@, @./mesh_001.usda@]"),
        "{stage}"
    );
    assert!(d.join("mesh.manifest.usda").exists());
    for f in 0..2 {
        let text = std::fs::read_to_string(d.join(format!("mesh_{f:03}.usda"))).unwrap();
        assert!(text.contains(&format!("points.timeSamples = {{\n            {f}: [")));
        assert!(text.contains("vector3f[] velocities.timeSamples"));
    }
    // the second shard of two, run again: its frame kept, the same stage written
    succeeded(&run(&["--shard", "2/2", "--skip-existing"]));
    assert_eq!(std::fs::read_to_string(d.join("mesh.usda")).unwrap(), stage);
    // a different file under the stage's name is not replaced without --force
    std::fs::write(d.join("mesh.usda"), "mine").unwrap();
    succeeded(&run(&["--force"]));
    assert_eq!(std::fs::read_to_string(d.join("mesh.usda")).unwrap(), stage);
    std::fs::write(d.join("mesh.usda"), "mine").unwrap();
    let out = bin()
        .args(["mesh", "--frames", "0..1", "--input"])
        .arg(d.join("c_{}.vtk"))
        .arg("--out")
        .arg(d.join("other_{}.usda"))
        .arg("--stage")
        .arg(d.join("mesh.usda"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(stderr_of(&out).contains("mesh.usda"), "{}", stderr_of(&out));
    assert_eq!(
        std::fs::read_to_string(d.join("mesh.usda")).unwrap(),
        "mine"
    );
    assert!(!d.join("other_0.usda").exists(), "refused before any work");
    // --stage without a .usda sequence
    let out = bin()
        .args(["mesh", "--scene", "sphere", "--stage", "x.usda"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(stderr_of(&out).contains("--stage"), "{}", stderr_of(&out));
}

/// `mesh --config FILE` reads a pipeline file under the flags: a file asking for splashsurf's
/// surface (the raw particles, `calibration = "volume"`, the cubic spline) gives the mesh the
/// library gives for the same parameters (triangle for triangle), and another one than the
/// flags alone; `--source` over the file's (here refused: `volume` is for the raw particles);
/// an unknown key named.
#[test]
fn mesh_reads_a_pipeline_file_under_the_flags() {
    use fluid_surfels::pipeline::{Pipeline, PipelineParams, Through};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let input = data("double_dam_break_frame_26_4732_particles.vtk");
    let config = d.join("splashsurf.toml");
    let text =
        "source = \"particles\"\n[grid]\nkernel = \"cubic-spline\"\ncalibration = \"volume\"\n";
    std::fs::write(&config, text).unwrap();
    let run = |extra: &[&str], out: &str| {
        bin()
            .args(["mesh", "--input", &input, "--json", "--out"])
            .arg(d.join(out))
            .args(extra)
            .output()
            .unwrap()
    };
    let with_file = json_of(&run(&["--config", config.to_str().unwrap()], "a.ply"));
    let flags = json_of(&run(
        &["--source", "particles", "--calibration", "volume"],
        "b.ply",
    ));
    // the library with the file's parameters, the radius the command estimates
    let set = fluid_surfels::io::read_particles(Path::new(&input), None).unwrap();
    let spacing = fluid_surfels::neighbours::estimate_spacing(&set.positions).unwrap();
    let mut params = PipelineParams::from_toml_file(&config).unwrap();
    params.support_radius = Some(2.0 * spacing);
    params.detail = fluid_surfels::pipeline::Detail::Fixed;
    let mesh = Pipeline::new(params)
        .unwrap()
        .frame_through(&set, Through::Mesh)
        .unwrap()
        .mesh
        .unwrap();
    assert_eq!(with_file["triangles"], mesh.triangles.len(), "{with_file}");
    assert_eq!(with_file["closed"], true);
    assert_ne!(
        with_file["triangles"], flags["triangles"],
        "the file's kernel unused"
    );
    let out = run(
        &["--config", config.to_str().unwrap(), "--source", "chain"],
        "c.ply",
    );
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains("source = \"particles\""), "{e}");
    let bad = d.join("bad.toml");
    std::fs::write(&bad, "[grid]\nkernl = \"wyvill\"\n").unwrap();
    let out = run(&["--config", bad.to_str().unwrap()], "d.ply");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("kernl"));
    assert!(!d.join("c.ply").exists() && !d.join("d.ply").exists());
}
