//! Incremental sessions through the command API: a pose graph streamed pose by pose is re-solved
//! in regions around each update, and must still end at the batch optimum.

mod common;

use common::server::g2o_batches;
use common::synthetic_manhattan;
use factord::api::wire::{Batch, CreateSession, SessionEvent};
use factord::service::{Command, Limits, Reply, Service};
use factord::solver::{optimize, SolverOptions};

#[tokio::test(flavor = "multi_thread")]
async fn streamed_pose_graph_is_resolved_in_regions_and_reaches_the_batch_optimum() {
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
        let (mut regions, mut full, mut skipped_acks) = (0, 0, 0);
        loop {
            let next = tokio::time::timeout(std::time::Duration::from_secs(2), events.recv()).await;
            let event = match next {
                Ok(Ok(event)) => event,
                Ok(Err(tokio::sync::broadcast::error::RecvError::Lagged(_))) => continue,
                _ => break,
            };
            match &*event {
                SessionEvent::Summary { summary, .. } => match summary.used.region_variables {
                    Some(n) => {
                        regions += 1;
                        assert!(n < 1500, "a region is part of the problem");
                    }
                    None => full += 1,
                },
                SessionEvent::Ack(ack) if ack.reflected => skipped_acks += 1,
                _ => {}
            }
        }
        (regions, full, skipped_acks)
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
    let (regions, full, skipped_acks) = collector.await.unwrap();
    assert!(
        regions > 10,
        "updates were re-solved in regions ({regions} regions, {full} full)"
    );
    assert!(skipped_acks > 100, "odometry-only updates need no solve");

    // The session's chi2 bookkeeping matches the true chi2 of its estimate (the initial chi2 of
    // a full solve from it), and that estimate is within 1e-4 of the batch optimum.
    let Reply::Stats(before) = service
        .execute(Command::GetStats {
            session: "walk".into(),
        })
        .await
        .unwrap()
    else {
        unreachable!()
    };
    let Reply::Optimizing {
        stats: Some(after), ..
    } = service
        .execute(Command::Optimize {
            session: "walk".into(),
            wait: true,
        })
        .await
        .unwrap()
    else {
        unreachable!()
    };
    let full_solve = after.last_summary.unwrap();
    assert_eq!(full_solve.used.region_variables, None);
    let tracked = before.chi2.unwrap();
    let true_chi2 = full_solve.initial_chi2;
    assert!(
        (tracked - true_chi2).abs() <= 1e-9 * true_chi2,
        "{tracked} vs {true_chi2}"
    );
    assert!(
        true_chi2 <= batch_chi2 * (1.0 + 1e-4),
        "streamed estimate {true_chi2} vs batch optimum {batch_chi2}"
    );
    assert!((full_solve.final_chi2 - batch_chi2).abs() <= 1e-6 * batch_chi2);
}
