//! Incremental sessions through the command API: a pose graph streamed pose by pose is updated
//! by the session's incremental engine (refactoring only what each update touches), polishes
//! itself when idle, and ends at the batch optimum.

use crate::common;

use common::server::g2o_batches;
use common::synthetic_manhattan;
use factord::api::wire::{Batch, CreateSession, SessionEvent};
use factord::api::{ApplyBatch, GetStats};
use factord::service::{Caller, Command, Limits, Recording, Reply, Service};
use factord::solver::incremental::UpdateReport;
use factord::solver::{optimize, SolverOptions};

#[tokio::test(flavor = "multi_thread")]
async fn streamed_pose_graph_is_updated_incrementally_and_reaches_the_batch_optimum() {
    let text = synthetic_manhattan(1500, 21);
    let mut graph = factord::io::parse_text(&text, std::path::Path::new("fixture"), None).unwrap();
    let batch_chi2 = optimize(&mut graph.problem, &SolverOptions::default(), &mut |_| {
        std::ops::ControlFlow::Continue(())
    })
    .unwrap()
    .final_chi2;

    let service = Service::new(Limits::default());
    service
        .execute(
            &Caller::Trusted,
            Command::CreateSession(CreateSession {
                session: Some("walk".into()),
                kind: "pose_graph_2d".into(),
                options: None,
                auto_optimize: Default::default(),
                factor_types: vec![],
                ros2: None,
                robots: None,
                outliers: Default::default(),
                max_update_ms: None,
            }),
            Recording::History,
        )
        .await
        .unwrap();
    // Count what the session streams, concurrently (the channel is bounded).
    let collector = summaries_until_quiet(service.session("walk").unwrap().subscribe());
    for b in g2o_batches(&text) {
        let batch: Batch = serde_json::from_value(b).unwrap();
        let reply = service
            .execute(
                &Caller::Trusted,
                Command::ApplyBatch(ApplyBatch {
                    session: "walk".into(),
                    batch,
                    wait: true,
                }),
                Recording::History,
            )
            .await
            .unwrap();
        let Reply::Accepted(a) = reply else {
            unreachable!()
        };
        assert_eq!(a.solved, Some(true));
    }
    let updates = collector.await.unwrap();
    let incremental = updates.iter().flatten().count();
    let full = updates.len() - incremental;
    let mut odometry_columns: Vec<usize> = updates
        .iter()
        .flatten()
        .filter(|u| u.new_factors == 1 && u.relinearized_variables == 0)
        .map(|u| u.refactored_columns)
        .collect();
    assert!(
        incremental > 1000 && full < 10,
        "updates were incremental ({incremental} incremental, {full} full solves)"
    );
    // An odometry step refactors the new pose and the root it hangs from, not the map.
    odometry_columns.sort_unstable();
    let median = odometry_columns[odometry_columns.len() / 2];
    assert!(
        median <= 3,
        "odometry updates refactored a median of {median} columns"
    );

    // Idle, the session polishes its estimate to convergence (the collector above waited 2 s).
    let Reply::Stats(stats) = service
        .execute(
            &Caller::Trusted,
            Command::GetStats(GetStats {
                session: "walk".into(),
            }),
            Recording::History,
        )
        .await
        .unwrap()
    else {
        unreachable!()
    };
    assert!(stats.converged, "the idle session polished to convergence");
    // The estimate it publishes is the batch optimum: its true chi2, evaluated on the batch
    // problem, and the chi2 the session reports.
    let Reply::Estimate(estimate) = service
        .execute(
            &Caller::Trusted,
            Command::get_estimate("walk".into(), Default::default()),
            Recording::History,
        )
        .await
        .unwrap()
    else {
        unreachable!()
    };
    let mut streamed = graph.problem;
    for v in &estimate.variables {
        let idx = streamed.values.index_of(v.key).unwrap();
        let pose = factord::geometry::Se2::new(v.value[0], v.value[1], v.value[2]);
        assert!(streamed.values.set(idx, &pose));
    }
    let true_chi2 = streamed.chi2();
    assert!(
        (true_chi2 - batch_chi2).abs() <= 1e-5 * batch_chi2,
        "streamed estimate {true_chi2} vs batch optimum {batch_chi2}"
    );
    let tracked = stats.chi2.unwrap();
    assert!(
        (tracked - true_chi2).abs() <= 1e-6 * true_chi2,
        "reported chi2 {tracked} vs true {true_chi2}"
    );
}

/// M3500's loop closures correct most of the map, one after another: streamed updates defer
/// relinearising those corrections (`UpdateParams::defer_from`, bounded by the session in
/// `session::incremental`), and once idle the estimate is still the batch optimum.
#[tokio::test(flavor = "multi_thread")]
async fn corrections_of_the_whole_map_are_deferred_and_the_idle_estimate_is_the_optimum() {
    let Some(path) = common::data_file("2d/carlone/input_M3500_g2o.g2o") else {
        return;
    };
    let text = std::fs::read_to_string(path).unwrap();
    let reference = batch_solved(&text, &[]);
    let batch_chi2 = reference.chi2();
    let service = Service::new(Limits::default());
    create_edits_session(&service).await;
    let collector = summaries_until_quiet(service.session("edits").unwrap().subscribe());
    for b in g2o_batches(&text) {
        apply(&service, serde_json::from_value(b).unwrap()).await;
    }
    let updates = collector.await.unwrap();
    let deferring: Vec<_> = updates
        .iter()
        .flatten()
        .filter(|u| u.deferred_variables > 0)
        .collect();
    for update in &deferring {
        assert_eq!(update.relinearized_variables, 0, "{update:?}");
    }
    let deferring = deferring.len();
    let relinearizing = updates
        .iter()
        .flatten()
        .filter(|u| u.relinearized_variables >= 1024)
        .count();
    println!("{deferring} updates deferred; {relinearizing} relinearised 1024 variables or more");
    assert!(deferring > 0, "no update deferred a correction");
    let idle = idle_chi2(&service, &reference).await;
    assert!(
        (idle - batch_chi2).abs() <= 1e-5 * batch_chi2,
        "idle estimate {idle} vs batch optimum {batch_chi2}"
    );
}

/// Collects, concurrently (the channel is bounded), what every solve summary of `events` says
/// of its incremental update (`None`: a full solve), until the session is quiet for 2 s.
fn summaries_until_quiet(
    mut events: tokio::sync::broadcast::Receiver<std::sync::Arc<factord::session::EventSlot>>,
) -> tokio::task::JoinHandle<Vec<Option<UpdateReport>>> {
    tokio::spawn(async move {
        let mut updates = Vec::new();
        loop {
            let next = tokio::time::timeout(std::time::Duration::from_secs(2), events.recv()).await;
            let event = match next {
                Ok(Ok(event)) => event,
                Ok(Err(tokio::sync::broadcast::error::RecvError::Lagged(_))) => continue,
                _ => break,
            };
            // An event the session took back was missed, as a lagged one is.
            let Some(event) = event.event() else {
                continue;
            };
            if let SessionEvent::Summary { summary, .. } = &*event {
                updates.push(summary.used.incremental.clone());
            }
        }
        updates
    })
}

/// Creates the 2D pose-graph session `edits` (which `apply` and `idle_chi2` use).
async fn create_edits_session(service: &Service) {
    run(
        service,
        Command::CreateSession(CreateSession {
            session: Some("edits".into()),
            kind: "pose_graph_2d".into(),
            options: None,
            auto_optimize: Default::default(),
            factor_types: vec![],
            ros2: None,
            robots: None,
            outliers: Default::default(),
            max_update_ms: None,
        }),
    )
    .await;
}

/// Runs a command that must succeed.
async fn run(service: &Service, command: Command) -> Reply {
    service
        .execute(&Caller::Trusted, command, Recording::History)
        .await
        .unwrap()
}

/// Applies `batch` to the session `edits` and waits for it to be reflected.
async fn apply(service: &Service, batch: Batch) -> Reply {
    let session = "edits".into();
    run(
        service,
        Command::ApplyBatch(ApplyBatch {
            session,
            batch,
            wait: true,
        }),
    )
    .await
}

/// Waits until the idle session has polished to convergence, then returns the true chi2 of its
/// estimate on `reference` (the same factors, solved in batch by the caller).
async fn idle_chi2(service: &Service, reference: &factord::problem::Problem) -> f64 {
    for _ in 0..500 {
        let Reply::Stats(stats) = run(
            service,
            Command::GetStats(GetStats {
                session: "edits".into(),
            }),
        )
        .await
        else {
            unreachable!()
        };
        if stats.converged && stats.solved_sequence == stats.sequence {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    }
    let Reply::Estimate(estimate) = run(
        service,
        Command::get_estimate("edits".into(), Default::default()),
    )
    .await
    else {
        unreachable!()
    };
    let mut values = reference.values.clone();
    for v in &estimate.variables {
        let idx = values.index_of(v.key).unwrap();
        assert!(values.set(
            idx,
            &factord::geometry::Se2::new(v.value[0], v.value[1], v.value[2])
        ));
    }
    factord::problem::evaluate_chi2(reference.factors(), &values).unwrap()
}

fn batch_solved(text: &str, fixed: &[(u64, [f64; 3])]) -> factord::problem::Problem {
    let mut graph = factord::io::parse_text(text, std::path::Path::new("fixture"), None).unwrap();
    for (key, value) in fixed {
        let idx = graph.problem.values.index_of(*key).unwrap();
        let pose = factord::geometry::Se2::new(value[0], value[1], value[2]);
        graph.problem.values.set(idx, &pose);
        graph.problem.set_fixed(*key, true).unwrap();
    }
    let options = SolverOptions {
        function_tolerance: 1e-12,
        ..Default::default()
    };
    optimize(&mut graph.problem, &options, &mut |_| {
        std::ops::ControlFlow::Continue(())
    })
    .unwrap();
    graph.problem
}

/// Removals, a guess and a fix after a streamed graph: each time the idle session's estimate
/// is the batch optimum of the factors it then holds (within 1e-5).
#[tokio::test(flavor = "multi_thread")]
async fn removals_guesses_and_fixes_keep_the_batch_optimum() {
    let text = synthetic_manhattan(600, 5);
    let service = Service::new(Limits::default());
    create_edits_session(&service).await;
    let mut loop_closures = Vec::new();
    for b in g2o_batches(&text) {
        let keys: Vec<(u64, u64)> = b["factors"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| {
                (
                    f["keys"][0].as_u64().unwrap(),
                    f["keys"][1].as_u64().unwrap(),
                )
            })
            .collect();
        let batch: Batch = serde_json::from_value(b).unwrap();
        let Reply::Accepted(ack) = apply(&service, batch).await else {
            unreachable!()
        };
        for (id, (a, b)) in ack.ack.factor_ids.iter().zip(keys) {
            if a + 1 != b {
                loop_closures.push((*id, a, b));
            }
        }
    }
    assert!(loop_closures.len() > 20, "the walk closes loops");
    let close = |chi2: f64, optimum: f64, what: &str| {
        assert!(
            (chi2 - optimum).abs() <= 1e-5 * optimum,
            "{what}: {chi2} vs batch {optimum}"
        );
    };
    let reference = batch_solved(&text, &[]);
    close(
        idle_chi2(&service, &reference).await,
        reference.chi2(),
        "streamed",
    );

    // Remove every other loop closure.
    let removed: Vec<_> = loop_closures.iter().step_by(2).collect();
    let batch = Batch {
        remove_factors: removed.iter().map(|r| r.0).collect(),
        ..Default::default()
    };
    apply(&service, batch).await;
    let drop: std::collections::HashSet<(u64, u64)> = removed.iter().map(|r| (r.1, r.2)).collect();
    let text: String = text
        .lines()
        .filter(|line| {
            let t: Vec<&str> = line.split_whitespace().collect();
            !(t.first() == Some(&"EDGE_SE2")
                && drop.contains(&(t[1].parse().unwrap(), t[2].parse().unwrap())))
        })
        .map(|l| format!("{l}\n"))
        .collect();
    let reference = batch_solved(&text, &[]);
    close(
        idle_chi2(&service, &reference).await,
        reference.chi2(),
        "after removals",
    );

    // A guess far off for one pose, then that pose fixed where the guess put it.
    let guess = [3.0, -2.0, 0.5];
    let batch: Batch = serde_json::from_value(serde_json::json!({
        "guesses": [{"key": 300, "value": guess}], "fix": [300]
    }))
    .unwrap();
    apply(&service, batch).await;
    let reference = batch_solved(&text, &[(300, guess)]);
    close(
        idle_chi2(&service, &reference).await,
        reference.chi2(),
        "after a guess and a fix",
    );

    // New poses keep streaming incrementally after the edits.
    let next: Batch = serde_json::from_value(serde_json::json!({
        "variables": [{"key": 600, "kind": "se2"}],
        "factors": [{"type": "between_se2", "keys": [599, 600], "measurement": [1.0, 0.0, 0.0],
                     "information": [100.0, 0.0, 0.0, 100.0, 0.0, 100.0]},
                    {"type": "between_se2", "keys": [1, 600], "measurement": [0.5, 0.5, 0.0],
                     "information": [1.0, 0.0, 0.0, 1.0, 0.0, 1.0]}]
    }))
    .unwrap();
    apply(&service, next).await;
    let Reply::Stats(stats) = run(
        &service,
        Command::GetStats(GetStats {
            session: "edits".into(),
        }),
    )
    .await
    else {
        unreachable!()
    };
    let last = stats.last_summary.expect("solved");
    assert!(
        last.used.incremental.is_some(),
        "an engine update after the edits"
    );
}
