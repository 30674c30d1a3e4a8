//! Incremental sessions through the command API: a pose graph streamed pose by pose is updated
//! by the session's incremental engine (refactoring only what each update touches), polishes
//! itself when idle, and ends at the batch optimum.

mod common;

use common::server::g2o_batches;
use common::synthetic_manhattan;
use factord::api::wire::{Batch, CreateSession, SessionEvent};
use factord::service::{Command, Limits, Reply, Service};
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
        .execute(Command::CreateSession(CreateSession {
            session: Some("walk".into()),
            kind: "pose_graph_2d".into(),
            options: None,
            auto_optimize: Default::default(),
        }))
        .await
        .unwrap();
    // Count what the session streams, concurrently (the channel is bounded).
    let mut events = service.session("walk").unwrap().subscribe();
    let collector = tokio::spawn(async move {
        let (mut incremental, mut full, mut odometry_columns) = (0, 0, Vec::new());
        loop {
            let next = tokio::time::timeout(std::time::Duration::from_secs(2), events.recv()).await;
            let event = match next {
                Ok(Ok(event)) => event,
                Ok(Err(tokio::sync::broadcast::error::RecvError::Lagged(_))) => continue,
                _ => break,
            };
            if let SessionEvent::Summary { summary, .. } = &*event {
                match &summary.used.incremental {
                    Some(update) => {
                        incremental += 1;
                        if update.new_factors == 1 && update.relinearized_variables == 0 {
                            odometry_columns.push(update.refactored_columns);
                        }
                    }
                    None => full += 1,
                }
            }
        }
        (incremental, full, odometry_columns)
    });
    for b in g2o_batches(&text) {
        let batch: Batch = serde_json::from_value(b).unwrap();
        let reply = service
            .execute(Command::ApplyBatch {
                session: "walk".into(),
                batch,
                wait: true,
            })
            .await
            .unwrap();
        let Reply::Accepted(a) = reply else {
            unreachable!()
        };
        assert_eq!(a.solved, Some(true));
    }
    let (incremental, full, mut odometry_columns) = collector.await.unwrap();
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
        .execute(Command::GetStats {
            session: "walk".into(),
        })
        .await
        .unwrap()
    else {
        unreachable!()
    };
    assert!(stats.converged, "the idle session polished to convergence");
    // The estimate it publishes is the batch optimum: its true chi2, evaluated on the batch
    // problem, and the chi2 the session reports.
    let Reply::Estimate(estimate) = service
        .execute(Command::GetEstimate {
            session: "walk".into(),
            since: None,
            from: None,
            to: None,
        })
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
