//! Side by side with the peer, splashsurf 0.14 (`splashsurf_lib`, a dev-dependency only), on the
//! same particles with the same kernel, support radius and cell size (`benches/common/peer.rs`):
//! the time of each reconstruction and their ratio, the peak memory of each, and how far our
//! surfels lie from splashsurf's mesh (mean and max distance, in cells), so that speed is never
//! bought with a different surface; then the meshes (issue 40): splashsurf's against ours (the
//! density grid, surfels and marching cubes), time, triangles, and the mean distance from each
//! mesh's vertices to the other, with our uniform weights and with the pipeline's `particles`
//! source at `calibration = "volume"` (splashsurf's per-particle volumes: the same density
//! field).
//!
//! ```text
//! cargo run --release --example peer_splashsurf                 # the 150k block and the real files
//! cargo run --release --example peer_splashsurf -- --small      # a 16^3 block (what CI runs)
//! cargo run --release --example peer_splashsurf -- --repeat 5   # best of 5 (default 3)
//! ```
//!
//! Each reconstruction runs in a child process of its own (this program run with `--child`), so
//! that its peak memory is its own: the child reads the particles, resets its peak resident set
//! (Linux `/proc/self/clear_refs`), reconstructs, and reports `VmHWM` (the particles, held
//! throughout, are part of every figure). Where the reset is not available the figure is the
//! whole child's peak, and says so.

#[path = "../benches/common/peer.rs"]
mod peer;

use std::process::Command;
use std::time::Instant;

use fluid_surfels::quality::MeshDistance;

const TOOLS: [&str; 5] = [
    "splashsurf",
    "ours-dense",
    "ours-sparse",
    "ours-mesh",
    "ours-grid-mesh",
];

fn case_by_name(name: &str) -> peer::Case {
    match name {
        "small" => peer::block("16^3 block", 16),
        _ => peer::cases()
            .into_iter()
            .find(|c| c.name == name)
            .unwrap_or_else(|| panic!("no case {name}")),
    }
}

/// The child: one tool on one case, `repeat` times; prints `best_ms peak_mib reset`.
fn child(tool: &str, case: &str, repeat: usize) {
    let c = case_by_name(case);
    let (input, params) = peer::peer_input(&c.positions, c.spacing);
    let reset = fluid_surfels::reset_peak_resident();
    let mut best = f64::INFINITY;
    for _ in 0..repeat {
        let t = Instant::now();
        let n = match tool {
            "splashsurf" => peer::splashsurf(&input, &params).len(),
            "ours-dense" => peer::ours_dense(&c.positions, c.spacing).len(),
            "ours-mesh" => peer::ours_mesh(&c.positions, c.spacing, true, None)
                .triangles
                .len(),
            "ours-grid-mesh" => peer::ours_grid_mesh(&c.positions, c.spacing)
                .triangles
                .len(),
            _ => peer::ours_sparse(&c.positions, c.spacing).len(),
        };
        best = best.min(t.elapsed().as_secs_f64() * 1e3);
        std::hint::black_box(n);
    }
    println!(
        "{best} {} {reset}",
        fluid_surfels::peak_resident_mib().unwrap_or(0.0)
    );
}

/// Runs the child for `tool` on `case`: (best ms, peak MiB, whether the peak is the tool's own).
fn measure(tool: &str, case: &str, repeat: usize) -> (f64, f64, bool) {
    let exe = std::env::current_exe().expect("this program's path");
    let out = Command::new(exe)
        .args(["--child", tool, case, &repeat.to_string()])
        .output()
        .expect("a child process");
    assert!(
        out.status.success(),
        "{tool} on {case}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    let f: Vec<&str> = text.split_whitespace().collect();
    (
        f[0].parse().expect("ms"),
        f[1].parse().expect("MiB"),
        f[2] == "true",
    )
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("--child") {
        child(&args[1], &args[2], args[3].parse().expect("a repeat count"));
        return;
    }
    let usage = || -> ! {
        eprintln!("usage: peer_splashsurf [--small] [--repeat N] (N >= 1, default 3)");
        std::process::exit(2)
    };
    let (mut repeat, mut small) = (3, false);
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--small" => small = true,
            "--repeat" => match it.next().and_then(|r| r.parse().ok()) {
                Some(n) if n >= 1 => repeat = n,
                _ => usage(),
            },
            _ => usage(),
        }
    }
    let names: Vec<String> = if small {
        vec!["small".into()]
    } else {
        peer::cases().iter().map(|c| c.name.to_string()).collect()
    };
    println!(
        "peer comparison: splashsurf 0.14 against our density grid + surfels, same kernel (cubic spline), radius 2 spacings, cells of 2/3 spacing, splashsurf's iso-value; {} threads, best of {repeat}",
        rayon::current_num_threads()
    );
    println!(
        "  {:<17} {:>9} | {:>16} | {:>16} | {:>16} | {:>8} {:>8} | surfels from its mesh, cells",
        "case", "particles", "splashsurf", "ours dense", "ours sparse", "dense", "sparse"
    );
    println!(
        "  {:<17} {:>9} | {:>7} {:>8} | {:>7} {:>8} | {:>7} {:>8} | {:>8} {:>8} | mean / max (dense, sparse)",
        "", "", "ms", "MiB", "ms", "MiB", "ms", "MiB", "speedup", "speedup"
    );
    let mut own_peaks = true;
    let mut mesh_rows = Vec::new();
    for name in &names {
        let m: Vec<(f64, f64, bool)> = TOOLS.iter().map(|t| measure(t, name, repeat)).collect();
        own_peaks &= m.iter().all(|x| x.2);
        let c = case_by_name(name);
        let (input, params) = peer::peer_input(&c.positions, c.spacing);
        let (_, cell) = peer::sizes(c.spacing);
        let mesh = MeshDistance::new(peer::splashsurf(&input, &params), cell);
        let theirs = peer::splashsurf_mesh(&input, &params);
        let both_ways = |ours: &fluid_surfels::mesh::Mesh| {
            (
                peer::mean_distance(ours, &theirs, cell),
                peer::mean_distance(&theirs, ours, cell),
            )
        };
        let ours = peer::ours_mesh(&c.positions, c.spacing, true, None);
        let (u1, u2) = both_ways(&ours);
        let weighted = peer::pipeline_mesh(
            &c.positions,
            c.spacing,
            fluid_surfels::pipeline::Calibration::Volume,
            false,
        );
        let (w1, w2) = both_ways(&weighted);
        let diff = |m: &fluid_surfels::mesh::Mesh| {
            100.0 * (m.triangles.len() as f64 / theirs.triangles.len() as f64 - 1.0)
        };
        let (l1, l2) = both_ways(&peer::ours_grid_mesh(&c.positions, c.spacing));
        mesh_rows.push(format!(
            "  {:<17} | {:>7.1} {:>8.1} | {:>7.1} {:>8.1} {:>6.2}x | {:>7.1} {:>8.1} {:>6.2}x | {:>8} {:>8} {:>+6.1} % | {u1:.3} / {u2:.3} | {l1:.3} / {l2:.3} | {w1:.3} / {w2:.3}, triangles {:+.1} %",
            c.name,
            m[0].0,
            m[0].1,
            m[3].0,
            m[3].1,
            m[0].0 / m[3].0,
            m[4].0,
            m[4].1,
            m[0].0 / m[4].0,
            theirs.triangles.len(),
            ours.triangles.len(),
            diff(&ours),
            diff(&weighted),
        ));
        let stats = |s: fluid_surfels::surfels::Surfels| {
            let d = mesh.distances(&s.positions);
            let mean = d.iter().map(|&x| f64::from(x)).sum::<f64>() / d.len().max(1) as f64;
            let max = d.iter().copied().fold(0.0f32, f32::max);
            (mean / f64::from(cell), f64::from(max / cell))
        };
        let (dm, dx) = stats(peer::ours_dense(&c.positions, c.spacing));
        let (sm, sx) = stats(peer::ours_sparse(&c.positions, c.spacing));
        println!(
            "  {:<17} {:>9} | {:>7.1} {:>8.1} | {:>7.1} {:>8.1} | {:>7.1} {:>8.1} | {:>7.2}x {:>7.2}x | {dm:.3} / {dx:.3}, {sm:.3} / {sx:.3}",
            c.name,
            c.positions.len(),
            m[0].0,
            m[0].1,
            m[1].0,
            m[1].1,
            m[2].0,
            m[2].1,
            m[0].0 / m[1].0,
            m[0].0 / m[2].0,
        );
    }
    println!(
        "meshes: splashsurf's whole reconstruction against ours: `exact` the density grid, surfels, marching cubes, vertices moved onto the surfels (Frame::mesh, the CLI's); `linear` the density grid and marching cubes alone, vertices on the grid's edges; uniform weights (the `particles` source)"
    );
    println!(
        "  {:<17} | {:>16} | {:>24} | {:>24} | {:>8} {:>8} {:>8} | mean distance, cells, ours->theirs / theirs->ours",
        "case", "splashsurf", "ours exact", "ours linear", "triangles", "", "",
    );
    println!(
        "  {:<17} | {:>7} {:>8} | {:>7} {:>8} {:>7} | {:>7} {:>8} {:>7} | {:>8} {:>8} {:>8} | exact | linear | the pipeline's `particles` source with calibration volume (splashsurf's field, m / rho_j)",
        "", "ms", "MiB", "ms", "MiB", "speedup", "ms", "MiB", "speedup", "theirs", "ours", "diff",
    );
    for row in &mesh_rows {
        println!("{row}");
    }
    println!(
        "  (MiB: peak resident set of a process holding the particles while it reconstructs{})",
        if own_peaks {
            ", reset before the reconstruction"
        } else {
            "; the reset is not available here, so each figure is the whole child process's peak"
        }
    );
}
