//! What the robots' own zenoh streams cost the server per solve (issue 54 item 4), for
//! benches/history/issue-54-robots.md: a measurement, ignored by default.

use crate::common;
use crate::robot_streams::{robots_session, samples};

use std::time::{Duration, Instant};

use common::server::{get, post, zenoh_peer, TestServer};
use common::square_walk::{closure, truth, INFO};
use factord::api::robots::robot_key;
use factord::geometry::Se2;
use serde_json::{json, Value};

const SESSION: &str = "rs";

/// Deterministic noise in [-1, 1] (a 64-bit LCG), so the measurement is repeatable.
struct Noise(u64);

impl Noise {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }
}

/// Robot `r`'s poses `range` (of a walk `offset` poses into the square), dead-reckoned from
/// noisy odometry in its own frame, with its odometry and a loop closure to the pose 40
/// before (the same place) every 10 poses.
fn noisy_robot_batch(
    r: char,
    world: &[Se2],
    range: std::ops::Range<usize>,
    reckoned: &mut Vec<Se2>,
    noise: &mut Noise,
) -> Value {
    let (mut variables, mut factors) = (Vec::new(), Vec::new());
    for i in range {
        let key = robot_key(r, i as u64);
        if i == 0 {
            reckoned.push(Se2::identity());
        } else {
            let z = world[i - 1].between(&world[i]);
            let z = Se2::new(
                z.x + 0.02 * noise.next(),
                z.y + 0.02 * noise.next(),
                z.theta + 0.01 * noise.next(),
            );
            reckoned.push(reckoned[i - 1].compose(&z));
            factors.push(
                json!({"type": "between_se2", "keys": [robot_key(r, i as u64 - 1), key],
                                "measurement": z.to_array(), "information": INFO}),
            );
        }
        if i >= 40 && i % 10 == 0 {
            factors.push(
                json!({"type": "between_se2", "keys": [robot_key(r, i as u64 - 40), key],
                                "measurement": world[i - 40].between(&world[i]).to_array(),
                                "information": INFO}),
            );
        }
        variables.push(json!({"key": key, "kind": "se2", "value": reckoned[i].to_array()}));
    }
    json!({"variables": variables, "factors": factors})
}

/// The cost of the robots' streams per solve, for benches/history/issue-54-robots.md: two
/// robots × 5000 poses streamed in batches of 100 (odometry with noise, a loop closure every
/// 10 poses, so each solve moves much of the map), merged on three closures after 300 poses;
/// read from the server's debug line per published run. `cargo test --release --test service
/// robot_streams_cost::measure -- --ignored --nocapture`.
#[tokio::test(flavor = "multi_thread")]
#[ignore = "a measurement (about a minute), not a check"]
async fn measure_the_robot_streams_cost_per_solve() {
    const POSES: usize = 5000;
    const BATCH: usize = 100;
    for subscribed in ["factord/rs/robot/*/**", "factord/rs/robot/a/bin/poses"] {
        let s = TestServer::start(&[
            "--log",
            "info,factord::transport::zenoh::robot_streams=debug",
        ]);
        let z = zenoh_peer(&s.zenoh).await;
        let c = robots_session(&s, SESSION).await;
        let url = |path: &str| s.url(&format!("/v1/sessions/{SESSION}{path}"));
        let (_sub, rx) = samples(&z, subscribed).await;
        tokio::time::sleep(Duration::from_millis(500)).await;
        let (a, b) = (truth(0, POSES), truth(13, POSES));
        let (mut reckoned_a, mut reckoned_b) = (Vec::new(), Vec::new());
        let mut noise = Noise(54);
        let started = Instant::now();
        for round in 0..POSES / BATCH {
            let range = round * BATCH..(round + 1) * BATCH;
            for (r, world, reckoned) in [('a', &a, &mut reckoned_a), ('b', &b, &mut reckoned_b)] {
                let body = noisy_robot_batch(r, world, range.clone(), reckoned, &mut noise);
                let (status, v) = post(&c, &url("/batches"), &body).await;
                assert_eq!(status, 200, "{v}");
            }
            if round == 3 {
                // b's pose j is where a's pose j + 13 is: three closures merge them.
                let closures: Vec<Value> = [(113usize, 100usize), (233, 220), (353, 340)]
                    .iter()
                    .map(|&(i, j)| closure(&a, i, &b, j))
                    .collect();
                let (status, v) = post(&c, &url("/batches"), &json!({"factors": closures})).await;
                assert_eq!(status, 200, "{v}");
            }
        }
        let (status, v) = post(&c, &url("/optimize?wait=true"), &json!({})).await;
        assert_eq!(status, 200, "{v}");
        let total = started.elapsed();
        tokio::time::sleep(Duration::from_secs(1)).await;
        let received = rx.try_iter().count();
        let (_, report) = get(&c, &url("/robots")).await;
        assert_eq!(report["merges"].as_array().unwrap().len(), 1, "{report}");
        let mut runs: Vec<(u64, u64, u64)> = s
            .stderr()
            .lines()
            .filter(|l| l.contains("robot streams published"))
            .filter_map(|l| {
                let field = |name: &str| -> Option<u64> {
                    let at = l.find(&format!("{name}="))? + name.len() + 1;
                    l[at..]
                        .split(|c: char| !c.is_ascii_digit())
                        .next()?
                        .parse()
                        .ok()
                };
                Some((field("micros")?, field("poses")?, field("puts")?))
            })
            .collect();
        assert!(!runs.is_empty(), "no debug lines: {}", s.stderr());
        runs.sort_unstable();
        let pick = |q: f64| runs[((runs.len() - 1) as f64 * q).round() as usize];
        let poses: u64 = runs.iter().map(|r| r.1).sum();
        let micros: u64 = runs.iter().map(|r| r.0).sum();
        println!(
            "subscribed {subscribed}: {} runs, {received} samples received, {poses} poses put in \
             {:.1} ms ({:.2} µs a pose); per run p50 {:?} p90 {:?} max {:?} (µs, poses, puts); \
             stream of 2 × {POSES} poses in {:.2} s",
            runs.len(),
            micros as f64 / 1000.0,
            micros as f64 / poses.max(1) as f64,
            pick(0.5),
            pick(0.9),
            runs.last().unwrap(),
            total.as_secs_f64()
        );
    }
}
