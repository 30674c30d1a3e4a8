//! Whether some subscriber would receive a put on a key now: a publisher declared on the key so
//! that zenoh keeps its matching status up to date (subscribers in this process, on a peer, or
//! behind a router), and a listener that keeps that status in a flag.
//!
//! The status arrives asynchronously: a publisher declared through a router learns of the
//! subscribers that match it only when the router answers (zenoh's interests), so a key can be
//! unheard when declared and heard a moment later with nothing else happening. Whoever needs to
//! act then (a robot's stream that starts whole) passes a [`Notify`] that the listener wakes,
//! and reads [`Heard::matched`] to tell a new audience from the one it already served.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;

use tokio::sync::Notify;

pub(super) struct Heard {
    status: Arc<Status>,
    _publisher: Option<zenoh::pubsub::Publisher<'static>>,
    _listener: Option<zenoh::matching::MatchingListener<()>>,
}

struct Status {
    /// Set as zenoh's matching status changes; stays true when zenoh refused the publisher or
    /// the listener (an unneeded put costs less than a lost one).
    heard: AtomicBool,
    /// How many times the key went from unheard to heard since it was declared.
    matched: AtomicU64,
    /// Woken each time the key becomes heard.
    wake: Option<Arc<Notify>>,
}

impl Status {
    fn set(&self, heard: bool) {
        let was = self.heard.swap(heard, Ordering::SeqCst);
        if heard && !was {
            self.matched.fetch_add(1, Ordering::SeqCst);
            if let Some(wake) = &self.wake {
                wake.notify_one();
            }
        }
    }
}

impl Heard {
    /// A publisher and its listener on `key`; `wake` is notified whenever the key becomes heard
    /// after it was declared.
    pub(super) async fn declare(
        zenoh: &zenoh::Session,
        key: String,
        wake: Option<Arc<Notify>>,
    ) -> Self {
        let status = Arc::new(Status {
            heard: AtomicBool::new(true),
            matched: AtomicU64::new(0),
            wake,
        });
        let (publisher, listener) = match zenoh.declare_publisher(key.clone()).await {
            Ok(publisher) => {
                let listener = listen(&publisher, &status).await;
                if listener.is_none() {
                    tracing::warn!(
                        "zenoh matching listener for {key} not declared: its events are \
                         put whether or not anyone subscribes"
                    );
                }
                (Some(publisher), listener)
            }
            Err(e) => {
                tracing::warn!(
                    "zenoh publisher for {key} not declared ({e}): its events are put \
                     whether or not anyone subscribes"
                );
                (None, None)
            }
        };
        Self {
            status,
            _publisher: publisher,
            _listener: listener,
        }
    }

    /// Whether some subscriber would receive a put on the key now.
    pub(super) fn now(&self) -> bool {
        self.status.heard.load(Ordering::SeqCst)
    }

    /// How many times the key became heard since it was declared: a subscriber that arrives
    /// after all others left changes it, so "served at this count" means served this audience.
    pub(super) fn matched(&self) -> u64 {
        self.status.matched.load(Ordering::SeqCst)
    }
}

/// A listener that keeps `status` up to date, `None` if zenoh refused it.
async fn listen(
    publisher: &zenoh::pubsub::Publisher<'static>,
    status: &Arc<Status>,
) -> Option<zenoh::matching::MatchingListener<()>> {
    let kept = Arc::clone(status);
    let listener = publisher
        .matching_listener()
        .callback(move |change| kept.set(change.matching()))
        .await
        .ok()?;
    // Read after the listener exists, so no change falls between the two. The flag starts
    // true (heard until told otherwise), so this read is not counted as a new audience.
    if let Ok(now) = publisher.matching_status().await {
        status.heard.store(now.matching(), Ordering::SeqCst);
    }
    Some(listener)
}
