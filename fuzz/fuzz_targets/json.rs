//! JSON message decoding as the transports do it (`factord::service::parse_json`) for a batch, a
//! command, a fusion batch and a create-session request. A decoded batch (alone, or inside an
//! `apply_batch` command) is then validated against a fresh, empty session of an in-process
//! `Service` (no network), and a decoded create-session request is tried on that service (which
//! checks the kind, name, solver options and auto-optimise policy). Sessions use the `manual`
//! policy, so nothing is ever solved, and are deleted after each input.
//!
//! Only panics are failures: rejections (`ServiceError`) are the expected outcome.
#![no_main]

use std::sync::Arc;

use factord::service::{parse_json, Command, Limits, Service};
use factord::session::fusion::FusionBatch;
use factord::session::wire::{AutoOptimize, Batch, CreateSession};
use factord_fuzz::verbose;
use libfuzzer_sys::fuzz_target;

const SESSION: &str = "fuzz";

struct Ctx {
    runtime: tokio::runtime::Runtime,
    service: Arc<Service>,
}

thread_local! {
    static CTX: Ctx = {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .expect("tokio runtime");
        let service = {
            let _guard = runtime.enter();
            Service::new(Limits {
                workers: 1,
                max_sessions: 4,
                max_pending_factors: 200_000,
                max_jobs: 1,
                wait_timeout_ms: 1_000,
                ..Limits::default()
            })
        };
        Ctx { runtime, service }
    };
}

impl Ctx {
    fn delete(&self, name: String) {
        self.runtime
            .block_on(self.service.execute(Command::DeleteSession { session: name }))
            .expect("deleting the session just created");
    }
}

/// The session kind a batch is meant for, guessed from its first variable or factor, so that
/// every kind's validation is reached (a batch of the wrong kind is rejected early).
fn kind_for(batch: &Batch) -> &'static str {
    let hint = batch
        .variables
        .first()
        .map(|v| v.kind.as_str())
        .or_else(|| batch.factors.first().map(|f| f.factor_type.as_str()))
        .unwrap_or("");
    if hint.contains("se3") {
        "pose_graph_3d"
    } else if hint.contains("snavely") || hint.contains("point3") {
        "bundle_adjustment"
    } else {
        "pose_graph_2d"
    }
}

fn validate_batch(batch: Batch) {
    CTX.with(|ctx| {
        let request = CreateSession {
            session: Some(SESSION.into()),
            kind: kind_for(&batch).into(),
            options: None,
            auto_optimize: AutoOptimize::Manual {},
        };
        ctx.service
            .create_session(request, None)
            .expect("creating an empty session");
        let session = ctx.service.session(SESSION).expect("the session just created");
        let result = session.apply_batch(batch);
        if verbose() {
            eprintln!("  apply_batch on an empty {}: {:?}", session.kind.name, result.map(|(ack, _)| ack));
        }
        drop(session);
        ctx.delete(SESSION.into());
    });
}

fn try_create(request: CreateSession) {
    CTX.with(|ctx| {
        let result = ctx.service.create_session(request, None);
        if verbose() {
            eprintln!("  create_session: {result:?}");
        }
        if let Ok(info) = result {
            ctx.delete(info.session);
        }
    });
}

fn outcome<T>(result: &Result<T, factord::service::ServiceError>) -> String {
    match result {
        Ok(_) => "ok".into(),
        Err(e) => format!("{}: {}", e.body.code, e.body.message),
    }
}

fuzz_target!(|data: &[u8]| {
    let batch = parse_json::<Batch>(data);
    let command = parse_json::<Command>(data);
    let fusion = parse_json::<FusionBatch>(data);
    let create = parse_json::<CreateSession>(data);
    if verbose() {
        eprintln!(
            "json: Batch {} | Command {} | FusionBatch {} | CreateSession {}",
            outcome(&batch),
            outcome(&command),
            outcome(&fusion),
            outcome(&create)
        );
    }
    if let Ok(batch) = batch {
        validate_batch(batch);
    }
    if let Ok(Command::ApplyBatch { batch, .. }) = command {
        validate_batch(batch);
    }
    if let Ok(request) = create {
        try_create(request);
    }
});
