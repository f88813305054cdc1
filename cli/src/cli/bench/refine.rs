//! `bench refine`: the upsampling of Table 1's frames, or of a file, parallel against the reference.

use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::neighbours::{Backend, Neighbourhoods};
use fluid_surfels::surface::{SurfaceDetector, SurfaceParams};
use serde::Serialize;

/// Arguments of `bench refine`.
#[derive(clap::Args)]
pub struct BenchRefineArgs {
    /// Timed repetitions per frame and implementation (the fastest is reported).
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// A particle file to refine instead of the column frames: its surface is detected, then
    /// each implementation runs as a `refine` child process of its own, so that the peak memory
    /// of each is measured apart (peak resident set of the child, input and detection included).
    #[arg(long)]
    pub input: Option<std::path::PathBuf>,
    /// Refinement steps with `--input` (the children get the same `--memory-budget`).
    #[arg(long, default_value_t = 4, requires = "input")]
    pub steps: u32,
}

/// One implementation's run on a file (`bench refine --input`).
#[derive(Serialize)]
struct FileRun {
    implementation: &'static str,
    points: u64,
    /// Fastest refinement of the runs, ms (detection and input not included).
    refine_ms: f64,
    /// Peak resident set of the first child, MiB (absent where the system does not report it).
    peak_rss_mib: Option<f64>,
}

/// `bench refine --input`: both implementations on one file, each in its own process.
fn bench_refine_file(args: &BenchRefineArgs, input: &std::path::Path) -> Result<(), Error> {
    let exe = std::env::current_exe().map_err(|e| Error::InvalidArgument {
        argument: "--input",
        reason: format!("cannot find this program to run its refine children: {e}"),
    })?;
    let mut runs = Vec::new();
    for (implementation, flag) in [("parallel", None), ("reference", Some("--reference"))] {
        let mut best: Option<FileRun> = None;
        for _ in 0..args.repeat.max(1) {
            let mut cmd = std::process::Command::new(&exe);
            cmd.arg("refine")
                .arg("--input")
                .arg(input)
                .args(["--steps", &args.steps.to_string()])
                .args([
                    "--memory-budget",
                    &crate::cli::memory_budget().to_string(),
                    "--json",
                ])
                .args(flag);
            let out = cmd.output().map_err(|e| Error::InvalidArgument {
                argument: "--input",
                reason: format!("cannot run the refine child: {e}"),
            })?;
            if !out.status.success() {
                return Err(Error::InvalidArgument {
                    argument: "--input",
                    reason: format!(
                        "the {implementation} refinement failed: {}",
                        String::from_utf8_lossy(&out.stderr)
                            .trim()
                            .trim_start_matches("error: ")
                    ),
                });
            }
            let v: serde_json::Value =
                serde_json::from_slice(&out.stdout).map_err(|e| Error::InvalidArgument {
                    argument: "--input",
                    reason: format!("the refine child's report does not parse: {e}"),
                })?;
            let run = FileRun {
                implementation,
                points: v["points"].as_u64().unwrap_or(0),
                refine_ms: v["refine_ms"].as_f64().unwrap_or(f64::NAN),
                peak_rss_mib: v["peak_rss_mib"].as_f64(),
            };
            best = Some(match best {
                Some(b) if b.refine_ms <= run.refine_ms => b,
                Some(b) => FileRun {
                    peak_rss_mib: b.peak_rss_mib,
                    ..run
                },
                None => run,
            });
        }
        runs.extend(best);
    }
    if runs[0].points != runs[1].points {
        return Err(Error::InvalidArgument {
            argument: "--input",
            reason: format!(
                "the implementations disagree: {} against {} points",
                runs[0].points, runs[1].points
            ),
        });
    }
    let report = serde_json::json!({
        "input": input.display().to_string(),
        "steps": args.steps,
        "threads": rayon::current_num_threads(),
        "runs": runs,
        "speedup": runs[1].refine_ms / runs[0].refine_ms,
    });
    if args.json {
        crate::cli::print_json(&report);
        return Ok(());
    }
    println!(
        "bench refine: {} in {} steps -> {} points, {} threads, fastest of {}, each in its own process",
        input.display(),
        args.steps,
        runs[0].points,
        rayon::current_num_threads(),
        args.repeat.max(1)
    );
    println!("  implementation   refinement ms   peak RSS MiB (whole process)");
    for r in &runs {
        let rss = r
            .peak_rss_mib
            .map_or_else(|| "not reported".to_string(), |m| format!("{m:.1}"));
        println!("  {:<15} {:>14.1}   {rss}", r.implementation, r.refine_ms);
    }
    println!(
        "  parallel against reference: {:.2}x the speed{}",
        runs[1].refine_ms / runs[0].refine_ms,
        match (runs[0].peak_rss_mib, runs[1].peak_rss_mib) {
            (Some(a), Some(b)) => format!(", {:.2}x the memory", a / b),
            _ => String::new(),
        }
    );
    Ok(())
}

#[derive(Serialize)]
struct RefineRow {
    name: &'static str,
    frame: usize,
    p0: usize,
    p3: usize,
    seconds: f64,
    points_per_second: f64,
    reference_seconds: f64,
    reference_points_per_second: f64,
    speedup: f64,
    /// Milliseconds per phase of the fastest parallel run, summed over its steps.
    phases: fluid_surfels::refine::StepPhases,
}

#[derive(Serialize)]
struct RefineBenchReport {
    threads: usize,
    steps: u32,
    points_per_second_means: &'static str,
    frames: Vec<RefineRow>,
}

/// Refines the surface of three `column` frames like the paper's Table 1 (initial block,
/// splashing, equilibrium) with the parallel and the reference implementation.
pub fn bench_refine(args: &BenchRefineArgs) -> Result<(), Error> {
    use fluid_surfels::refine::{RefineParams, refine, refine_reference};
    if let Some(input) = &args.input {
        return bench_refine_file(args, input);
    }
    use fluid_surfels::scenes::{ColumnParams, ColumnSim};
    let frames = [
        ("initial block", ColumnParams::INITIAL_FRAME),
        ("splashing", ColumnParams::SPLASH_FRAME),
        ("equilibrium", ColumnParams::EQUILIBRIUM_FRAME),
    ];
    let mut sim = ColumnSim::new(ColumnParams::default())?;
    let mut detector = SurfaceDetector::new(SurfaceParams::default())?;
    let mut inputs = Vec::new();
    for f in 0..=ColumnParams::EQUILIBRIUM_FRAME {
        sim.advance_to(f);
        let nb = Neighbourhoods::build(
            &sim.particles().positions,
            sim.support_radius(),
            Backend::CellGrid,
        )?;
        let surface = detector.detect(sim.particles(), &nb)?;
        if let Some((name, _)) = frames.iter().find(|x| x.1 == f) {
            let (p, n) = crate::cli::refine::surface_of(sim.particles(), &surface);
            inputs.push((*name, f, p, n));
        }
    }
    let params = RefineParams::with_radius(sim.support_radius());
    let mut rows = Vec::new();
    for (name, frame, p, n) in inputs {
        let mut best = f64::INFINITY;
        let mut best_ref = f64::INFINITY;
        let mut p3 = 0;
        let mut phases = fluid_surfels::refine::StepPhases::default();
        for _ in 0..args.repeat.max(1) {
            let t = Instant::now();
            let r = refine(&p, &n, &params)?;
            let seconds = t.elapsed().as_secs_f64();
            if seconds < best {
                // the phases of the fastest run
                phases = r
                    .stats
                    .iter()
                    .fold(Default::default(), |a, s| s.phases.plus(a));
            }
            best = best.min(seconds);
            p3 = r.len();
            let t = Instant::now();
            let r = refine_reference(&p, &n, &params)?;
            best_ref = best_ref.min(t.elapsed().as_secs_f64());
            assert_eq!(r.len(), p3, "the implementations disagree");
        }
        rows.push(RefineRow {
            name,
            frame,
            p0: p.len(),
            p3,
            seconds: best,
            points_per_second: p3 as f64 / best,
            reference_seconds: best_ref,
            reference_points_per_second: p3 as f64 / best_ref,
            speedup: best_ref / best,
            phases,
        });
    }
    let report = RefineBenchReport {
        threads: rayon::current_num_threads(),
        steps: params.steps,
        points_per_second_means: "P3 / seconds, as the paper's Table 1",
        frames: rows,
    };
    if args.json {
        crate::cli::print_json(&report);
    } else {
        println!(
            "bench refine: column frames like Table 1, 3 steps, {} threads, fastest of {}",
            report.threads,
            args.repeat.max(1)
        );
        println!(
            "  frame              P0      P3    parallel s   points/s    reference s   points/s   speedup"
        );
        for r in &report.frames {
            println!(
                "  {:<14} {:>6} {:>7}   {:>9.4} {:>10.0}   {:>11.4} {:>10.0}   {:>6.2}x",
                r.name,
                r.p0,
                r.p3,
                r.seconds,
                r.points_per_second,
                r.reference_seconds,
                r.reference_points_per_second,
                r.speedup
            );
        }
        println!("  (points/s = P3 / seconds, as in the paper's Table 1)");
        println!(
            "  the parallel run's phases, ms over its steps: candidates | type 2 checks + registration lists | type 3 rivals (parallel) + decisions (sequential) | update: moves (sequential) + neighbourhoods"
        );
        for r in &report.frames {
            let p = r.phases;
            println!(
                "  {:<14} {:>8.1} {:>8.1} {:>8.1} {:>8.1} = {:.1} + {:.1}",
                r.name,
                p.candidates_ms,
                p.type2_ms,
                p.accept_ms,
                p.update_ms,
                p.moves_ms,
                p.update_ms - p.moves_ms
            );
        }
    }
    Ok(())
}
