//! The `factord` batch commands end to end: real files in, real files out, real pipes.

use crate::common;

use std::process::Command;

use common::cli::{factord, Run};

#[test]
fn solve_writes_summary_json_graph_and_trajectory() {
    let dir = common::temp_dir("cli");
    let input = dir.join("in.g2o");
    std::fs::write(&input, common::synthetic_manhattan(120, 9)).unwrap();
    let (summary, out, tum) = (dir.join("s.json"), dir.join("out.g2o"), dir.join("t.txt"));
    let output = factord()
        .arg("solve")
        .arg(&input)
        .args(["--method", "lm", "--max-iterations", "50", "--summary-json"])
        .arg(&summary)
        .arg("--out")
        .arg(&out)
        .arg("--tum")
        .arg(&tum)
        .succeeds();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        stdout.contains("iter   1") && stdout.contains("termination:"),
        "{stdout}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
    for field in [
        "initial_chi2",
        "final_chi2",
        "iterations",
        "solve_seconds",
        "method",
        "termination",
    ] {
        assert!(json.get(field).is_some(), "summary lacks {field}");
    }
    assert_eq!(json["method"], "levenberg_marquardt");
    let final_chi2 = json["final_chi2"].as_f64().unwrap();
    assert!(final_chi2 < json["initial_chi2"].as_f64().unwrap());
    // The written graph re-reads with the optimised chi2, and the trajectory has one line a pose.
    let mut reread = factord::io::load(&out, None).unwrap();
    assert!((reread.problem.chi2() - final_chi2).abs() <= 1e-6 * final_chi2);
    // One line a pose after the header that says the first column is the vertex id.
    let tum = std::fs::read_to_string(&tum).unwrap();
    assert!(tum.starts_with("# vertex_id "), "{tum}");
    assert_eq!(tum.lines().count(), 1 + 120);
    let again = factord::solver::optimize(&mut reread.problem, &Default::default(), &mut |_| {
        std::ops::ControlFlow::Continue(())
    })
    .unwrap();
    assert!(again.final_chi2 <= final_chi2 * (1.0 + 1e-6));
}

#[test]
fn bad_input_exits_with_an_error_not_a_panic() {
    let dir = common::temp_dir("cli-bad");
    let input = dir.join("bad.g2o");
    std::fs::write(
        &input,
        "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n",
    )
    .unwrap();
    let stderr = factord().arg("solve").arg(&input).refused();
    assert!(
        stderr.contains("bad.g2o:2:") && stderr.contains("unknown variable 1"),
        "{stderr}"
    );
    assert!(!stderr.contains("panicked"));
    let output = factord()
        .args(["solve", "/nonexistent/file.g2o"])
        .output()
        .unwrap();
    assert_eq!(output.status.code(), Some(2));
    let output = factord()
        .arg("solve")
        .arg(&input)
        .args(["--method", "newton"])
        .output()
        .unwrap();
    assert!(!output.status.success());
}

#[test]
fn ba_runs_the_course_workflow_and_writes_point_clouds() {
    let Some(input) = common::data_file("bal/problem-49-7776-pre.txt") else {
        return;
    };
    let dir = common::temp_dir("ba");
    let (summary, before, after, out) = (
        dir.join("s.json"),
        dir.join("before.ply"),
        dir.join("after.ply"),
        dir.join("out.txt"),
    );
    factord()
        .arg("ba")
        .arg(&input)
        .args([
            "--normalize",
            "--perturb",
            "0.1,0.5,0.5",
            "--seed",
            "3",
            "--robust",
            "huber:1.0",
        ])
        .args(["--quiet", "--summary-json"])
        .arg(&summary)
        .arg("--ply-initial")
        .arg(&before)
        .arg("--ply-final")
        .arg(&after)
        .arg("--out")
        .arg(&out)
        .succeeds();
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
    let (initial, last) = (
        s["initial_cost"].as_f64().unwrap(),
        s["final_cost"].as_f64().unwrap(),
    );
    assert!(last < 0.05 * initial, "{initial} -> {last}");
    assert!(s["converged"].as_bool().unwrap(), "{s}");
    for ply in [&before, &after] {
        let text = std::fs::read_to_string(ply).unwrap();
        assert!(
            text.contains("element vertex 7825"),
            "7776 points + 49 cameras"
        );
        assert_eq!(text.lines().count(), 7825 + 11);
    }
    // The written BAL file reads back at the final cost.
    let back = factord::io::bal::load(&out).unwrap();
    let mut with_kernel = back;
    with_kernel
        .problem
        .set_robust_kernel(Some(factord::factors::RobustKernel::Huber(1.0)));
    assert!((with_kernel.cost() - last).abs() <= 1e-6 * last);
}

#[test]
fn ba_rejects_a_bad_file_with_a_clear_error() {
    let dir = common::temp_dir("ba-bad");
    let input = dir.join("bad.txt");
    std::fs::write(&input, "2 1 1\n0 3 1.0 2.0\n").unwrap();
    let err = factord().arg("ba").arg(&input).refused();
    assert!(
        err.contains("bad.txt") && err.contains("the file has"),
        "{err}"
    );
    assert!(!err.contains("panicked"));
}

#[test]
fn solve_plot_draws_initial_guess_optimum_loop_closures_and_convergence() {
    let dir = common::temp_dir("cli-plot");
    let input = dir.join("in.g2o");
    let text = common::synthetic_manhattan(150, 4);
    std::fs::write(&input, &text).unwrap();
    let (plot, summary) = (dir.join("before_after.svg"), dir.join("s.json"));
    factord()
        .arg("solve")
        .arg(&input)
        .args(["--init", "none", "--quiet", "--plot"])
        .arg(&plot)
        .arg("--summary-json")
        .arg(&summary)
        .succeeds();
    let svg = std::fs::read_to_string(&plot).unwrap();
    assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
    // Two trajectories, with one vertex per pose each.
    let polylines: Vec<&str> = svg.lines().filter(|l| l.starts_with("<polyline")).collect();
    assert_eq!(polylines.len(), 2);
    for p in &polylines {
        let points = p
            .split("points=\"")
            .nth(1)
            .unwrap()
            .split_whitespace()
            .count();
        assert_eq!(points, 150, "{}", &p[..80]);
    }
    let loops = text
        .lines()
        .filter(|l| {
            let t: Vec<u64> = l
                .split_whitespace()
                .skip(1)
                .take(2)
                .map(|k| k.parse().unwrap_or(0))
                .collect();
            l.starts_with("EDGE_SE2") && t[0].abs_diff(t[1]) != 1
        })
        .count();
    assert!(loops > 10);
    assert!(svg.contains(&format!("loop closures ({loops})")), "{loops}");
    // One marker per iteration and one for the initial guess (plus hollow ones for rejections).
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
    let log = json["iteration_log"].as_array().unwrap();
    let rejected = log.iter().filter(|r| r["accepted"] == false).count();
    assert_eq!(svg.matches("<circle").count(), 1 + log.len() + rejected);

    // A path that cannot be written is an error naming it, not a panic.
    let bad = dir.join("missing-dir/x.svg");
    let stderr = factord()
        .arg("solve")
        .arg(&input)
        .args(["--quiet", "--plot"])
        .arg(&bad)
        .refused();
    assert!(
        stderr.contains("missing-dir/x.svg") && !stderr.contains("panicked"),
        "{stderr}"
    );
}

/// Progress shows on a terminal (a pseudo-terminal from util-linux `script`) and nothing of
/// it appears when the output is piped.
#[test]
fn progress_shows_on_a_terminal_and_stays_quiet_when_piped() {
    let dir = common::temp_dir("cli-progress");
    let input = dir.join("in.g2o");
    std::fs::write(&input, common::synthetic_manhattan(300, 5)).unwrap();
    let command = format!(
        "{} solve {}",
        env!("CARGO_BIN_EXE_factord"),
        input.display()
    );

    let piped = Command::new(env!("CARGO_BIN_EXE_factord"))
        .arg("solve")
        .arg(&input)
        .output()
        .unwrap();
    assert!(piped.status.success());
    assert!(
        piped.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&piped.stderr)
    );
    let stdout = String::from_utf8_lossy(&piped.stdout);
    assert!(stdout.contains("iter   1"));
    assert!(!stdout.contains('\r') && !stdout.contains('\u{1b}') && !stdout.contains("solving ["));

    let typescript = dir.join("typescript");
    let tty = match Command::new("script")
        .args(["-qfec", &command])
        .arg(&typescript)
        .output()
    {
        Ok(out) => out,
        Err(e) => {
            common::skip_or_fail::<()>(&format!("no `script` (util-linux) for a terminal: {e}"));
            return;
        }
    };
    assert!(
        tty.status.success(),
        "{}",
        String::from_utf8_lossy(&tty.stderr)
    );
    let screen = std::fs::read_to_string(&typescript).unwrap();
    assert!(
        screen.contains("loading ") && screen.contains("solving ["),
        "{screen}"
    );
    assert!(screen.contains("iteration 1/100 chi2"), "{screen}");
    // The iteration lines still reach the terminal, above the bar.
    assert!(
        screen.contains("iter   1") && screen.contains("termination:"),
        "{screen}"
    );
}

fn run_with_stdin(command: &mut Command, stdin: &[u8]) -> std::process::Output {
    use std::io::Write;
    let mut child = command
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // A command that refuses its arguments exits before reading: a broken pipe is its answer.
    let _ = child.stdin.take().unwrap().write_all(stdin);
    child.wait_with_output().unwrap()
}

/// `-` is standard input and output; with data on stdout the progress lines go to stderr; two
/// `-` outputs and bad piped input are errors naming the argument or `<stdin>`.
#[test]
fn dash_reads_stdin_and_writes_stdout_with_progress_on_stderr() {
    let text = common::synthetic_manhattan(80, 2);
    let output = run_with_stdin(
        factord().args(["solve", "-", "--out", "-"]),
        text.as_bytes(),
    );
    let (stdout, stderr) = (
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr),
    );
    assert!(output.status.success(), "{stderr}");
    assert!(
        stderr.contains("loaded <stdin>") && stderr.contains("iter   1"),
        "{stderr}"
    );
    let graph = factord::io::parse_text(&stdout, "out".as_ref(), None).unwrap();
    assert_eq!(
        graph.problem.values.len(),
        80,
        "stdout holds only the graph"
    );

    let output = run_with_stdin(
        factord().args(["solve", "-", "--out", "-", "--tum", "-"]),
        text.as_bytes(),
    );
    assert_eq!(output.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("--tum") && stderr.contains("already taken by --out"),
        "{stderr}"
    );

    let output = run_with_stdin(
        factord().args(["solve", "-"]),
        b"VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n",
    );
    assert_eq!(output.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("<stdin>:2:") && !stderr.contains("panicked"),
        "{stderr}"
    );

    // The Summary on stdout is the whole of stdout.
    let output = run_with_stdin(
        factord().args(["solve", "-", "--summary-json", "-"]),
        text.as_bytes(),
    );
    assert!(output.status.success());
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(json["input"], "<stdin>");
}

/// `solve --tum` says its first column is the vertex id, or takes stamps from `--stamps`, and
/// writes every number in shortest round-trip form.
#[test]
fn solve_tum_writes_ids_with_a_header_or_stamps_from_a_file() {
    let dir = common::temp_dir("cli-tum");
    let input = dir.join("in.g2o");
    std::fs::write(&input, common::synthetic_manhattan(30, 3)).unwrap();
    let stamps = dir.join("stamps.txt");
    let lines: String = (0..30)
        .map(|i| format!("{i} 1403715273.{:09}\n", 262142944 + i))
        .collect();
    std::fs::write(&stamps, lines).unwrap();
    let output = factord()
        .arg("solve")
        .arg(&input)
        .args(["--quiet", "--tum", "-", "--stamps"])
        .arg(&stamps)
        .succeeds();
    let tum = String::from_utf8(output.stdout).unwrap();
    let mut rows = tum.lines();
    assert_eq!(rows.next(), Some("# timestamp tx ty tz qx qy qz qw"));
    let first: Vec<&str> = rows.next().unwrap().split(' ').collect();
    assert_eq!(first[0], "1403715273.262142944", "stamps keep every digit");
    for row in tum.lines().skip(1) {
        for number in row.split(' ').skip(1) {
            let value: f64 = number.parse().unwrap();
            assert_eq!(value.to_string(), number, "not shortest round-trip: {row}");
        }
    }
    // A pose without a stamp is an error naming the stamps file and the vertex.
    std::fs::write(&stamps, "0 1.5\n").unwrap();
    let stderr = factord()
        .arg("solve")
        .arg(&input)
        .args(["--quiet", "--tum", "-", "--stamps"])
        .arg(&stamps)
        .refused();
    assert!(
        stderr.contains("stamps.txt") && stderr.contains("no stamp for vertex 1"),
        "{stderr}"
    );
    // --stamps without --tum is refused by the argument parser.
    let output = factord()
        .arg("solve")
        .arg(&input)
        .arg("--stamps")
        .arg(&stamps)
        .output()
        .unwrap();
    assert!(!output.status.success());
}

/// FACTORD_DATA: relative inputs not found here are looked up there, fusion-eval's default
/// dataset lives there, and a missing one is an error naming the argument and the variable.
#[test]
fn factord_data_locates_inputs_and_default_datasets() {
    let data = common::temp_dir("cli-data-root");
    std::fs::create_dir_all(data.join("graphs")).unwrap();
    std::fs::write(
        data.join("graphs/m.g2o"),
        common::synthetic_manhattan(40, 1),
    )
    .unwrap();
    let elsewhere = common::temp_dir("cli-data-cwd");
    let output = factord()
        .current_dir(&elsewhere)
        .env("FACTORD_DATA", &data)
        .args(["solve", "graphs/m.g2o", "--quiet", "--summary-json", "-"])
        .succeeds();
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(json["num_variables"], 40);

    let stderr = factord()
        .current_dir(&elsewhere)
        .env("FACTORD_DATA", &data)
        .args(["solve", "graphs/missing.g2o"])
        .refused();
    assert!(
        stderr.contains("graph graphs/missing.g2o") && stderr.contains("FACTORD_DATA"),
        "{stderr}"
    );

    let stderr = factord()
        .env("FACTORD_DATA", &data)
        .arg("fusion-eval")
        .refused();
    let expected = data.join("imu/euroc_V1_01_easy");
    assert!(
        stderr.contains("--data") && stderr.contains(&*expected.to_string_lossy()),
        "{stderr}"
    );
    assert!(!stderr.contains("panicked"));
}

/// evo reads what `solve --tum --stamps` writes (header comment, stamps, shortest round-trip
/// numbers): two solves of one graph agree, and evo_ape says so.
#[test]
fn evo_ape_reads_solve_tum_with_stamps() {
    let python = match common::python_venv("evo", &[vec!["evo".into()]]) {
        Ok(python) => python,
        Err(e) => return common::skip_or_fail::<()>(&format!("no evo: {e}")).unwrap_or(()),
    };
    let dir = common::temp_dir("cli-evo");
    let input = dir.join("helix.g2o");
    std::fs::write(&input, common::synthetic_helix_3d(50, 4)).unwrap();
    let stamps = dir.join("stamps.txt");
    let lines: String = (0..50)
        .map(|i| format!("{i} {}\n", 1000.0 + 0.1 * i as f64))
        .collect();
    std::fs::write(&stamps, lines).unwrap();
    let (gn, lm) = (dir.join("gn.tum"), dir.join("lm.tum"));
    for (method, tum) in [("gn", &gn), ("lm", &lm)] {
        factord()
            .arg("solve")
            .arg(&input)
            .args(["--quiet", "--method", method, "--tum"])
            .arg(tum)
            .arg("--stamps")
            .arg(&stamps)
            .succeeds();
    }
    let output = Command::new(python.with_file_name("evo_ape"))
        .arg("tum")
        .arg(&gn)
        .arg(&lm)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let rmse: f64 = stdout
        .lines()
        .find_map(|l| l.trim().strip_prefix("rmse"))
        .unwrap_or_else(|| panic!("{stdout}"))
        .trim()
        .parse()
        .unwrap();
    assert!(rmse < 1e-3, "{stdout}");
}

/// `ba --threads 2` solves a BAL problem on two threads to one thread's cost (the Summary says
/// two were used); a count beyond 256 or not a number is refused naming the flag.
#[test]
fn ba_threads_solve_alike_and_a_bad_count_is_refused() {
    let Some(input) = common::data_file("bal/problem-49-7776-pre.txt") else {
        return;
    };
    let dir = common::temp_dir("ba-threads");
    let mut costs = Vec::new();
    for threads in ["1", "2"] {
        let summary = dir.join(format!("s{threads}.json"));
        factord()
            .arg("ba")
            .arg(&input)
            .args(["--quiet", "--threads", threads, "--summary-json"])
            .arg(&summary)
            .succeeds();
        let s: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
        assert_eq!(
            s["used"]["threads"].as_u64(),
            Some(threads.parse().unwrap())
        );
        assert_eq!(
            s["given_options"]["threads"].as_u64(),
            Some(threads.parse().unwrap())
        );
        costs.push(s["final_cost"].as_f64().unwrap());
    }
    assert!(
        (costs[0] - costs[1]).abs() <= 1e-9 * costs[0],
        "one thread {} against two {}",
        costs[0],
        costs[1]
    );
    for bad in ["257", "-1", "two"] {
        let err = factord()
            .arg("ba")
            .arg(&input)
            .arg(format!("--threads={bad}"))
            .refused();
        assert!(
            err.contains("--threads") && err.contains("256"),
            "{bad}: {err}"
        );
    }
}

/// `ba --linear-solver iterative_schur` solves with the implicit Schur complement (conjugate
/// gradients, S never formed), says so in its report and Summary, and reaches the explicit
/// solve's optimum; an unknown solver is refused with the list that includes it.
#[test]
fn ba_iterative_schur_reaches_the_explicit_optimum_and_says_so() {
    let Some(input) = common::data_file("bal/problem-49-7776-pre.txt") else {
        return;
    };
    let dir = common::temp_dir("ba-implicit");
    let mut costs = Vec::new();
    for solver in ["auto", "iterative_schur"] {
        let summary = dir.join(format!("{solver}.json"));
        let report = factord()
            .arg("ba")
            .arg(&input)
            .args(["--linear-solver", solver, "--summary-json"])
            .arg(&summary)
            .succeeds();
        let s: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
        let schur = &s["used"]["schur"];
        if solver == "iterative_schur" {
            assert_eq!(schur["reduced_factorization"], "implicit", "{s}");
            assert!(schur["cg_iterations"].as_u64().unwrap() > 0, "{s}");
            let report = String::from_utf8_lossy(&report.stdout);
            assert!(
                report.contains("Linear solver: implicit Schur complement, conjugate gradients"),
                "the report names the solver: {report}"
            );
        } else {
            assert_eq!(schur["reduced_factorization"], "dense", "{s}");
            assert!(schur.get("cg_iterations").is_none(), "{s}");
        }
        costs.push(s["final_cost"].as_f64().unwrap());
    }
    assert!(
        (costs[0] - costs[1]).abs() <= 1e-6 * costs[0],
        "explicit {} against implicit {}",
        costs[0],
        costs[1]
    );
    let err = factord()
        .arg("ba")
        .arg(&input)
        .args(["--linear-solver", "pcg"])
        .refused();
    assert!(err.contains("iterative_schur"), "{err}");
}
