//! Direct (photometric) bundle adjustment on the course's data: 7 images, 4118 point patches.

use crate::common;

use std::process::Command;

#[test]
fn direct_ba_lowers_every_images_patch_difference() {
    let Some(poses) = common::data_file("direct_ba/poses.txt") else {
        return;
    };
    let dir = poses.parent().unwrap().to_path_buf();
    let out = common::temp_dir("direct-ba");
    let (summary, before, after) = (
        out.join("summary.json"),
        out.join("before.ply"),
        out.join("after.ply"),
    );
    let output = Command::new(env!("CARGO_BIN_EXE_factord"))
        .arg("direct-ba")
        .arg(&dir)
        .arg("--summary-json")
        .arg(&summary)
        .arg("--ply-initial")
        .arg(&before)
        .arg("--ply-final")
        .arg(&after)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
    assert_eq!(json["converged"], true, "{stdout}");
    assert_eq!(json["used"]["schur"]["eliminated_variables"], 4118);
    assert_eq!(json["used"]["schur"]["reduced_factorization"], "dense");
    let (initial, last) = (
        json["initial_chi2"].as_f64().unwrap(),
        json["final_chi2"].as_f64().unwrap(),
    );
    assert!(last < 0.8 * initial, "cost {initial} -> {last}");
    assert!(json["successful_steps"].as_u64().unwrap() >= 2);
    let images = |key: &str| -> Vec<(f64, u64)> {
        json[key]
            .as_array()
            .unwrap()
            .iter()
            .map(|a| {
                (
                    a["mean_abs_patch_difference"].as_f64().unwrap(),
                    a["points_visible"].as_u64().unwrap(),
                )
            })
            .collect()
    };
    let (start, end) = (images("agreement_before"), images("agreement_after"));
    assert_eq!(start.len(), 7);
    // The data's README measured 14–23 gray levels per image at the given poses.
    for (i, ((b, nb), (a, na))) in start.iter().zip(&end).enumerate() {
        assert!((13.0..24.0).contains(b), "image {i}: {b} before");
        assert!(a < b, "image {i}: {b} -> {a}");
        assert!(*nb > 2000 && *na > 2000, "image {i}: {nb} -> {na} points");
    }
    for ply in [&before, &after] {
        let text = std::fs::read_to_string(ply).unwrap();
        assert!(text.contains("element vertex 4125\n"), "{ply:?}");
        assert!(text.contains("element edge 6\n"), "{ply:?}");
    }
}

#[test]
fn bad_direct_ba_input_is_a_clear_error() {
    let dir = common::temp_dir("direct-ba-bad");
    let run = |dir: &std::path::Path| {
        let output = Command::new(env!("CARGO_BIN_EXE_factord"))
            .arg("direct-ba")
            .arg(dir)
            .output()
            .unwrap();
        assert!(!output.status.success());
        String::from_utf8_lossy(&output.stderr).to_string()
    };
    std::fs::write(dir.join("poses.txt"), "0 0 0 0 0 0 0 1\n").unwrap();
    std::fs::write(dir.join("points.txt"), "0 0 1 1 2 3\n").unwrap();
    let e = run(&dir);
    assert!(
        e.contains("points.txt:1") && e.contains("expected 19 numbers"),
        "{e}"
    );
    std::fs::write(
        dir.join("points.txt"),
        format!("0 0 1{}\n", " 5".repeat(16)),
    )
    .unwrap();
    std::fs::write(dir.join("poses.txt"), "0 0 0 nan 0 0 0 1\n").unwrap();
    let e = run(&dir);
    assert!(e.contains("poses.txt:1") && e.contains("not finite"), "{e}");
    std::fs::write(dir.join("poses.txt"), "0 0 0 0 0 0 0 1\n").unwrap();
    let e = run(&dir);
    assert!(e.contains("0.png"), "{e}");
    std::fs::write(dir.join("0.png"), "not a png").unwrap();
    let e = run(&dir);
    assert!(
        e.contains("0.png") && e.contains("not a readable PNG"),
        "{e}"
    );
}
