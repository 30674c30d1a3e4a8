//! What the `factord` batch commands print and draw: `ba`'s Ceres rows, plots with axes and side
//! views as SVG and PNG, `fusion-eval`'s text report and `--json`.

use crate::common;

use common::cli::{factord, Run};

/// `ba` prints Ceres' rows (cost = ½Σρ, the same numbers as the Summary) and Ceres' cost block;
/// with `--summary-json -` the JSON is all of stdout and the rows go to stderr.
#[test]
fn ba_prints_ceres_rows_and_summary() {
    let Some(input) = common::data_file("bal/problem-49-7776-pre.txt") else {
        return;
    };
    let output = factord()
        .arg("ba")
        .arg(&input)
        .args(["--max-iterations", "4", "--summary-json", "-"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let header = "iter      cost      cost_change  |gradient|   |step|    tr_ratio  tr_radius  ls_iter  iter_time  total_time";
    assert!(stderr.contains(header), "{stderr}");
    let rows: Vec<Vec<f64>> = stderr
        .lines()
        .skip_while(|l| *l != header)
        .skip(1)
        .take_while(|l| !l.is_empty())
        .map(|l| l.split_whitespace().map(|t| t.parse().unwrap()).collect())
        .collect();
    let log = json["iteration_log"].as_array().unwrap();
    assert_eq!(rows.len(), 1 + log.len());
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-6 * b.abs();
    assert!(close(rows[0][1], json["initial_cost"].as_f64().unwrap()));
    for (row, report) in rows[1..].iter().zip(log) {
        assert!(
            close(row[1], report["chi2"].as_f64().unwrap() / 2.0),
            "{row:?}"
        );
        assert!(
            (row[5] - report["gain_ratio"].as_f64().unwrap()).abs() < 0.01,
            "{row:?}"
        );
    }
    assert!(close(
        rows.last().unwrap()[1],
        json["final_cost"].as_f64().unwrap()
    ));
    assert!(stderr.contains("\nCost:\nInitial  "), "{stderr}");
    assert!(stderr.contains("Termination:"), "{stderr}");
}

/// Plots: tick labels on the axes, 3D from above and from the side, PNG to a file or stdout.
#[test]
fn plots_have_axes_side_views_and_png() {
    let dir = common::temp_dir("cli-plot3d");
    let input = dir.join("helix.g2o");
    std::fs::write(&input, common::synthetic_helix_3d(60, 2)).unwrap();
    let (svg_path, png_path) = (dir.join("p.svg"), dir.join("p.png"));
    for plot in [&svg_path, &png_path] {
        factord()
            .arg("solve")
            .arg(&input)
            .args(["--quiet", "--plot"])
            .arg(plot)
            .succeeds();
    }
    let svg = std::fs::read_to_string(&svg_path).unwrap();
    assert!(svg.contains(">from above<") && svg.contains(">from the side<"));
    assert!(svg.contains(">x (m)<") && svg.contains(">y (m)<") && svg.contains(">z (m)<"));
    assert_eq!(
        svg.lines().filter(|l| l.starts_with("<polyline")).count(),
        4
    );
    let ticks = svg.matches(r#"font-size="11">"#).count();
    assert!(ticks >= 10, "{ticks} tick labels");

    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(&png_path).unwrap(),
    ));
    let mut reader = decoder.read_info().unwrap();
    let mut pixels = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut pixels).unwrap();
    let width: f64 = svg
        .split("width=\"")
        .nth(1)
        .unwrap()
        .split('"')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert_eq!(info.width as f64, width);
    let drawn = pixels
        .chunks(4)
        .filter(|p| p[0] < 200 || p[2] < 200)
        .count();
    assert!(drawn > 2000, "{drawn} drawn pixels: an empty picture?");

    let output = factord()
        .arg("solve")
        .arg(&input)
        .args(["--quiet", "--plot", "-", "--plot-format", "png"])
        .output()
        .unwrap();
    assert!(output.status.success());
    assert!(output.stdout.starts_with(b"\x89PNG\r\n\x1a\n"));
}

/// fusion-eval prints a text report; JSON only with --json, which then owns stdout.
#[test]
fn fusion_eval_prints_text_unless_asked_for_json() {
    let Some(imu) = common::data_file("imu/euroc_V1_01_easy/imu0.csv") else {
        return;
    };
    let data = imu.parent().unwrap();
    let run = |extra: &[&str]| {
        factord()
            .args(["fusion-eval", "--seconds", "4", "--window", "3", "--data"])
            .arg(data)
            .args(extra)
            .output()
            .unwrap()
    };
    let text = run(&[]);
    let stdout = String::from_utf8_lossy(&text.stdout);
    assert!(
        text.status.success(),
        "{}",
        String::from_utf8_lossy(&text.stderr)
    );
    assert!(stdout.contains("APE translation (m)") && stdout.contains("update (ms)"));
    assert!(serde_json::from_str::<serde_json::Value>(&stdout).is_err());
    let json = run(&["--json"]);
    let value: serde_json::Value = serde_json::from_slice(&json.stdout).unwrap();
    assert!(value["ape_trans"]["rmse"].is_number());
    let both = run(&["--json", "--tum-out", "-"]);
    assert_eq!(both.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&both.stderr).contains("--tum-out"));
    let tum = run(&["--tum-out", "-"]);
    assert!(String::from_utf8_lossy(&tum.stdout).starts_with("# timestamp"));
    assert!(String::from_utf8_lossy(&tum.stderr).contains("APE translation"));
}

/// bench-cholesky prints a table, JSON only with --json, and the matrix alone on stdout with
/// `--write-mtx -` (the table then on stderr).
#[test]
fn bench_cholesky_prints_a_table_json_on_request_and_the_matrix_to_stdout() {
    let dir = common::temp_dir("cli-bench-cholesky");
    let input = dir.join("m.g2o");
    std::fs::write(&input, common::synthetic_manhattan(50, 1)).unwrap();
    let run = |extra: &[&str]| {
        let output = factord()
            .arg("bench-cholesky")
            .arg(&input)
            .args(["--repeat", "2"])
            .args(extra)
            .succeeds();
        (
            String::from_utf8(output.stdout).unwrap(),
            String::from_utf8(output.stderr).unwrap(),
        )
    };
    let (table, _) = run(&[]);
    assert!(
        table.contains("supernodal") && serde_json::from_str::<serde_json::Value>(&table).is_err()
    );
    let (json, _) = run(&["--json"]);
    let json: serde_json::Value = serde_json::from_str(&json).unwrap();
    let n = json["n"].as_u64().unwrap();
    assert_eq!(n, 3 * 49, "one pose fixed for the gauge");
    assert!(json["supernodal"]["solve_seconds"].as_f64().unwrap() > 0.0);
    let (mtx, table) = run(&["--write-mtx", "-"]);
    assert!(mtx.starts_with("%%MatrixMarket matrix coordinate real symmetric\n"));
    assert_eq!(
        mtx.lines().count() as u64,
        2 + json["nnz_lower"].as_u64().unwrap()
    );
    assert!(table.contains("supernodal"), "{table}");
}

/// Victoria Park (GTSAM's landmark text) through `solve --out`: the g2o written reads back as the
/// same problem (every pose, landmark, odometry and bearing-range sighting) at the optimum's χ²;
/// the plot draws the poses as the line and the landmarks as dots apart from it.
#[test]
fn a_landmark_graph_round_trips_through_out_and_plots_landmarks_as_dots() {
    let Some(input) = common::data_file("2d/gtsam/victoria_park.txt") else {
        return;
    };
    let dir = common::temp_dir("cli-landmark-out");
    let (out, summary, plot) = (
        dir.join("vp.g2o"),
        dir.join("summary.json"),
        dir.join("vp.svg"),
    );
    factord()
        .arg("solve")
        .arg(&input)
        .args(["--quiet", "--max-iterations", "8", "--out"])
        .arg(&out)
        .arg("--summary-json")
        .arg(&summary)
        .arg("--plot")
        .arg(&plot)
        .succeeds();
    let original = factord::io::load(&input, None).unwrap();
    let written = factord::io::load(&out, None).unwrap();
    let count = |graph: &factord::io::PoseGraph, kind: &str| {
        let values = &graph.problem.values;
        (0..values.len())
            .filter(|&v| values.variable(v).kind() == kind)
            .count()
    };
    for kind in ["se2", "point2"] {
        assert_eq!(count(&written, kind), count(&original, kind), "{kind}");
    }
    assert_eq!(count(&original, "point2"), 151);
    assert_eq!(
        written.problem.factors().len(),
        original.problem.factors().len()
    );
    let sightings = |graph: &factord::io::PoseGraph| {
        graph
            .problem
            .factors()
            .iter()
            .filter(|f| f.factor.keys().len() == 2 && f.factor.residual_dim() == 2)
            .count()
    };
    assert_eq!(sightings(&written), sightings(&original));
    assert!(sightings(&original) >= 3640, "{}", sightings(&original));

    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
    let optimum = summary["final_chi2"].as_f64().unwrap();
    let read_back = written.problem.chi2();
    assert!(
        (read_back - optimum).abs() <= 1e-9 * optimum,
        "χ² read back {read_back} vs the optimum's {optimum}"
    );
    // The original problem at the written values scores the same: the factors are the same.
    let mut at_written = original;
    for v in 0..written.problem.values.len() {
        let key = written.problem.values.key(v);
        let value = written.problem.values.variable(v).clone_box();
        let index = at_written.problem.values.index_of(key).expect("same keys");
        assert!(at_written
            .problem
            .values
            .variable_mut(index)
            .assign_from(value.as_ref()));
    }
    let original_chi2 = at_written.problem.chi2();
    assert!(
        (original_chi2 - optimum).abs() <= 1e-9 * optimum,
        "the original problem at the written values: {original_chi2} vs {optimum}"
    );
    eprintln!("victoria_park round trip: χ² {optimum} (read back {read_back})");

    let svg = std::fs::read_to_string(&plot).unwrap();
    let optimum_line = svg
        .lines()
        .filter(|l| l.starts_with("<polyline"))
        .nth(1)
        .expect("the optimum's line");
    let points = optimum_line.split("points=\"").nth(1).unwrap();
    assert_eq!(
        points.split(' ').count(),
        count(&written, "se2"),
        "the line is the poses only"
    );
    let dots = svg
        .lines()
        .find(|l| l.contains(r#"class="landmarks""#))
        .expect("landmarks drawn as dots");
    assert_eq!(dots.matches('M').count(), 151);
    // Its odometry is a chain over pose ids that skip the landmarks' old ids: no loop closure.
    assert!(
        svg.contains("loop closures (0)"),
        "{}",
        &svg[svg.len() - 600..]
    );
}
