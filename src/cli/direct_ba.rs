//! `factord direct-ba`: direct (photometric) bundle adjustment of the course's images, poses and
//! point patches, reporting how well the patches agree with the images before and after.

use std::path::PathBuf;
use std::time::Instant;

use factord::factors::RobustKernel;
use factord::geometry::image::Pinhole;
use factord::io;
use factord::solver::SolverOptions;

use super::data_dir;
use super::progress::Progress;
use super::solve_output::{optimize_verbose, write_summary_json, IterationLines};
use super::stdio::{Console, OutputArg};
use super::value_parsers::parse_robust;
use super::CliError;

#[derive(clap::Args)]
pub struct DirectBaArgs {
    /// Directory with poses.txt, points.txt and 0.png, 1.png, … (a relative path not found here
    /// is looked up under $FACTORD_DATA)
    dir: PathBuf,
    /// Pinhole intrinsics fx,fy,cx,cy [default: those of the Shenlan visual SLAM course's PA7
    /// framework, 277.34,291.402,312.234,239.777]
    #[arg(long, value_parser = parse_intrinsics)]
    intrinsics: Option<Pinhole>,
    /// Robust kernel on every patch residual (16 gray levels), e.g. huber:40 or none
    #[arg(long, default_value = "huber:40", value_parser = parse_optional_robust)]
    robust: OptionalRobust,
    /// Stop after this many iterations (the solve then reports it did not converge)
    #[arg(long, default_value_t = 100)]
    max_iterations: usize,
    /// Stop when an accepted step lowers χ² by less than this fraction of it (0: never)
    #[arg(long, default_value_t = 1e-6)]
    function_tolerance: f64,
    /// Write the Summary plus the per-image patch agreement before and after as JSON; `-` for
    /// standard output.
    #[arg(long)]
    summary_json: Option<OutputArg>,
    /// Points and camera trajectory before and after, as PLY; `-` for standard output.
    #[arg(long)]
    ply_initial: Option<OutputArg>,
    /// Points and camera trajectory after the solve, as PLY; `-` for standard output.
    #[arg(long)]
    ply_final: Option<OutputArg>,
    /// Print only errors
    #[arg(long)]
    quiet: bool,
}

fn parse_intrinsics(s: &str) -> Result<Pinhole, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("`{s}`: {e} (expected fx,fy,cx,cy)"))?;
    match v[..] {
        [fx, fy, cx, cy] if v.iter().all(|x| x.is_finite()) && fx > 0.0 && fy > 0.0 => {
            Ok(Pinhole { fx, fy, cx, cy })
        }
        _ => Err(format!(
            "`{s}`: expected four finite numbers fx,fy,cx,cy with fx, fy > 0"
        )),
    }
}

/// A robust kernel or `none` (clap reads a bare `Option` field as "flag may be absent").
#[derive(Clone, Copy)]
struct OptionalRobust(Option<RobustKernel>);

fn parse_optional_robust(s: &str) -> Result<OptionalRobust, String> {
    if s == "none" {
        return Ok(OptionalRobust(None));
    }
    parse_robust(s).map(|k| OptionalRobust(Some(k)))
}

pub fn run(args: DirectBaArgs) -> Result<(), CliError> {
    let outputs = [
        ("--summary-json", args.summary_json.as_ref()),
        ("--ply-initial", args.ply_initial.as_ref()),
        ("--ply-final", args.ply_final.as_ref()),
    ];
    let console = Console::for_outputs(&outputs, args.quiet)?;
    let dir = data_dir::existing_dir("dir", &args.dir)?;
    let start = Instant::now();
    let camera = args.intrinsics.unwrap_or(io::direct_ba::COURSE_CAMERA);
    let loading = Progress::loading(&dir, args.quiet);
    let problem = io::direct_ba::load(&dir, camera, args.robust.0);
    loading.finish();
    let mut problem = problem?;
    let load_seconds = start.elapsed().as_secs_f64();
    let before = problem.agreement();
    if let Some(target) = &args.ply_initial {
        let ply = io::ply::trajectory_to_string(&problem.points(), &problem.camera_centres());
        target.write("--ply-initial", ply.as_bytes())?;
    }
    console.print(&format!(
            "loaded {} ({} images, {} points, {} point-image factors, {} points seen by no image) in {load_seconds:.3}s\n",
            dir.display(),
            problem.num_poses(),
            problem.num_points(),
            problem.problem.factors().len(),
            problem.unseen_points,
        ));
    let options = SolverOptions {
        max_iterations: args.max_iterations,
        function_tolerance: args.function_tolerance,
        ..SolverOptions::bundle_adjustment()
    };
    let summary = optimize_verbose(
        &mut problem.problem,
        &options,
        console,
        IterationLines::Chi2,
    )?;
    let after = problem.agreement();
    {
        let mut report = summary.report();
        report += &format!(
            "cost (Σρ(‖r‖²), gray levels²): {:.6e} -> {:.6e}, {} accepted steps\n",
            summary.initial_chi2, summary.final_chi2, summary.successful_steps
        );
        report += "mean |patch − image| per image (gray levels), before -> after:\n";
        for (b, a) in before.iter().zip(&after) {
            report += &format!(
                "  image {}: {:.2} ({} points) -> {:.2} ({} points)\n",
                b.image,
                b.mean_abs_patch_difference,
                b.points_visible,
                a.mean_abs_patch_difference,
                a.points_visible
            );
        }
        console.print(&report);
    }
    if let Some(target) = &args.summary_json {
        write_summary_json(
            target,
            &summary,
            vec![
                ("input", dir.display().to_string().into()),
                ("load_seconds", load_seconds.into()),
                ("agreement_before", serde_json::to_value(&before)?),
                ("agreement_after", serde_json::to_value(&after)?),
            ],
        )?;
    }
    if let Some(target) = &args.ply_final {
        let ply = io::ply::trajectory_to_string(&problem.points(), &problem.camera_centres());
        target.write("--ply-final", ply.as_bytes())?;
    }
    Ok(())
}
