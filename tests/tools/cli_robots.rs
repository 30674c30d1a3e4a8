//! Files of several robots (issue 54): a g2o file whose poses are keyed by robot (GTSAM's
//! `Symbol('a', i)` = `('a' << 56) | i`), each robot's values in its own start frame, edges
//! across robots as closures. `factord solve` and a batch job reach the optimum of the same
//! graph as one robot, and `solve` reports each robot's `map ← odom`.

use crate::common;

use common::cli::factord;
use common::server::{client, post_raw, TestServer};
use factord::geometry::{Se2, Se3};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};

/// The file cut into `robots` contiguous robots: vertex `v` becomes pose `v − start` of robot
/// `a`, `b`, …, its value expressed in its robot's first pose's frame; edges keep their
/// measurements with renamed ends.
fn split_into_robots(text: &str, robots: usize) -> String {
    let vertices: Vec<Vec<&str>> = text
        .lines()
        .map(|l| l.split_whitespace().collect::<Vec<_>>())
        .filter(|t| t.first().is_some_and(|tag| tag.starts_with("VERTEX")))
        .collect();
    let n = vertices.len();
    let robot_of = |pos: usize| (pos * robots / n).min(robots - 1);
    let mut key = std::collections::HashMap::new();
    let mut starts: Vec<Option<usize>> = vec![None; robots];
    for (pos, t) in vertices.iter().enumerate() {
        let r = robot_of(pos);
        let start = *starts[r].get_or_insert(pos);
        let id: u64 = t[1].parse().unwrap();
        key.insert(id, ((b'a' + r as u8) as u64) << 56 | (pos - start) as u64);
    }
    let num = |t: &[&str]| -> Vec<f64> { t.iter().map(|x| x.parse().unwrap()).collect() };
    let mut out = String::new();
    let mut origin2: Vec<Option<Se2>> = vec![None; robots];
    let mut origin3: Vec<Option<Se3>> = vec![None; robots];
    for (pos, t) in vertices.iter().enumerate() {
        let r = robot_of(pos);
        let k = key[&t[1].parse::<u64>().unwrap()];
        let f = num(&t[2..]);
        if t[0] == "VERTEX_SE2" {
            let p = Se2::new(f[0], f[1], f[2]);
            let o = *origin2[r].get_or_insert(p.inverse());
            let q = o.compose(&p);
            out += &format!("VERTEX_SE2 {k} {} {} {}\n", q.x, q.y, q.theta);
        } else {
            let rotation = UnitQuaternion::from_quaternion(Quaternion::new(f[6], f[3], f[4], f[5]));
            let p = Se3::new(rotation, Vector3::new(f[0], f[1], f[2]));
            let o = *origin3[r].get_or_insert(p.inverse());
            let q = o.compose(&p);
            let (t, r) = (q.translation, q.rotation);
            out += &format!(
                "VERTEX_SE3:QUAT {k} {} {} {} {} {} {} {}\n",
                t.x, t.y, t.z, r.i, r.j, r.k, r.w
            );
        }
    }
    for line in text.lines() {
        let t: Vec<&str> = line.split_whitespace().collect();
        if t.first().is_some_and(|tag| tag.starts_with("EDGE")) {
            let (i, j) = (key[&t[1].parse().unwrap()], key[&t[2].parse().unwrap()]);
            out += &format!("{} {i} {j} {}\n", t[0], t[3..].join(" "));
        }
    }
    out
}

/// `factord solve FILE --summary-json -`, parsed.
fn solve_json(path: &std::path::Path) -> serde_json::Value {
    let output = factord()
        .arg("solve")
        .arg(path)
        .args(["--summary-json", "-"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    serde_json::from_slice(&output.stdout).unwrap()
}

fn relative(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs().max(1e-300)
}

#[test]
fn solve_reaches_the_one_robot_optimum_and_reports_each_robots_frame() {
    for (file, robots) in [
        ("2d/carlone/input_M3500_g2o.g2o", 3),
        ("3d/sesync/sphere2500.g2o", 4),
    ] {
        let Some(path) = common::data_file(file) else {
            return;
        };
        let text = std::fs::read_to_string(&path).unwrap();
        let dir = common::temp_dir("cli-robots");
        let split = dir.join("robots.g2o");
        std::fs::write(&split, split_into_robots(&text, robots)).unwrap();
        let one = solve_json(&path);
        let many = solve_json(&split);
        let (a, b) = (
            one["final_chi2"].as_f64().unwrap(),
            many["final_chi2"].as_f64().unwrap(),
        );
        assert!(relative(b, a) < 1e-6, "{file}: {b} vs one robot's {a}");
        let views = many["robots"].as_array().expect("robots reported");
        assert_eq!(views.len(), robots, "{file}");
        let names: String = views.iter().map(|v| v["robot"].as_str().unwrap()).collect();
        assert_eq!(names, "abcd"[..robots], "{file}");
        // The map is robot a's frame: its transform is the identity.
        let first: Vec<f64> = serde_json::from_value(views[0]["map_from_odom"].clone()).unwrap();
        let identity: &[f64] = if first.len() == 3 {
            &[0.0, 0.0, 0.0]
        } else {
            &[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
        };
        assert!(
            first
                .iter()
                .zip(identity)
                .all(|(x, y)| (x - y).abs() < 1e-9),
            "{file}: {first:?}"
        );
        let poses: u64 = views.iter().map(|v| v["poses"].as_u64().unwrap()).sum();
        let vertices = text.lines().filter(|l| l.starts_with("VERTEX")).count();
        assert_eq!(poses as usize, vertices);
    }
}

#[test]
fn a_batch_job_of_several_robots_reaches_the_same_optimum() {
    let Some(path) = common::data_file("2d/carlone/input_M3500_g2o.g2o") else {
        return;
    };
    let text = std::fs::read_to_string(&path).unwrap();
    let s = TestServer::start(&[]);
    let c = client();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let (status, one) = rt.block_on(post_raw(&c, &s.url("/v1/jobs"), text.clone()));
    assert_eq!(status, 200, "{one}");
    let (status, many) = rt.block_on(post_raw(
        &c,
        &s.url("/v1/jobs"),
        split_into_robots(&text, 2),
    ));
    assert_eq!(status, 200, "{many}");
    let (a, b) = (
        one["summary"]["final_chi2"].as_f64().unwrap(),
        many["summary"]["final_chi2"].as_f64().unwrap(),
    );
    assert!(relative(b, a) < 1e-6, "{b} vs {a}");
    // The robots' keys come back exact (beyond f64's integers).
    let keys: Vec<u64> = many["estimate"]["variables"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["key"].as_u64().unwrap())
        .collect();
    assert!(
        keys.contains(&((b'b' as u64) << 56 | 1749)),
        "{:?}",
        &keys[..3]
    );
    s.assert_no_panic();
}
