//! The binding's subscriptions: odometry, absolute poses and IMU samples, in the order they
//! arrive, decoded from CDR, turned into batches by the [`Keyframer`] (pose graphs) or fusion
//! messages by the [`WindowFeed`] (sliding windows), and executed as any client's commands.
//!
//! A message that cannot be used (not CDR of the expected type, a bad covariance, a prior
//! before any keyframe) is counted and reported on the session's error stream (SSE, zenoh
//! `out/errors`) with code `ros2_bad_message`; nothing of it reaches the session.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;

use super::attachment::{Attachment, AttachmentError};
use super::cdr_codec;
use super::keyframes::{Keyframer, MessageError};
use super::messages::{
    Imu, Odometry, PoseWithCovarianceStamped, IMU, ODOMETRY, POSE_WITH_COVARIANCE_STAMPED,
};
use super::tf::TfBroadcaster;
use super::window_feed::{Feed, WindowFeed};
use crate::api::wire::Batch;
use crate::service::{Caller, Command, Delivery, Service, ServiceError};

pub(super) type Samples = Subscriber<FifoChannelHandler<Sample>>;

/// Why a ROS message was not used.
#[derive(Debug, thiserror::Error)]
enum Unusable {
    #[error(transparent)]
    Cdr(#[from] cdr_codec::CdrError),
    #[error(transparent)]
    Message(#[from] MessageError),
    #[error(transparent)]
    Attachment(#[from] AttachmentError),
}

/// What turns messages into commands: keyframes of a pose graph, or a window's fusion feed.
pub(super) enum Feeder {
    Graph(Keyframer),
    /// Boxed: several times a keyframer's size (clippy: large_enum_variant).
    Window(Box<WindowFeed>),
}

/// The binding's input topics.
#[derive(Clone, Copy)]
enum Topic {
    Odometry,
    Prior,
    Imu,
}

impl Topic {
    fn field(self) -> &'static str {
        match self {
            Topic::Odometry => "ros2.odometry_topic",
            Topic::Prior => "ros2.prior_topic",
            Topic::Imu => "ros2.imu_topic",
        }
    }
}

pub(super) struct Inputs {
    pub service: Arc<Service>,
    pub caller: Arc<Caller>,
    pub session: String,
    pub feeder: Feeder,
    pub odometry: Samples,
    pub priors: Option<Samples>,
    pub imu: Option<Samples>,
    /// Told of every odometry message used and every keyframe made (`map → odom` on `/tf`).
    pub tf: Option<Arc<TfBroadcaster>>,
    /// Messages refused so far (reported with each refusal).
    pub refused: Arc<AtomicU64>,
}

/// The next sample of an optional subscription (never, without one).
async fn next(samples: &Option<Samples>) -> Result<Sample, zenoh::Error> {
    match samples {
        Some(samples) => samples.recv_async().await,
        None => std::future::pending().await,
    }
}

impl Inputs {
    /// Takes messages until the subscriptions end (the binding is dropped).
    pub async fn run(mut self) {
        loop {
            let (sample, topic) = tokio::select! {
                s = self.odometry.recv_async() => (s, Topic::Odometry),
                s = next(&self.priors) => (s, Topic::Prior),
                s = next(&self.imu) => (s, Topic::Imu),
            };
            let Ok(sample) = sample else { return };
            let payload = sample.payload().to_bytes();
            // rmw_zenoh always attaches one; a sample without (a plain zenoh put) is taken, one
            // with something else is not from rmw_zenoh and is refused.
            let used = match sample
                .attachment()
                .map(|a| Attachment::decode(&a.to_bytes()))
            {
                Some(Err(e)) => Err(e.into()),
                _ => self.take(topic, &payload).await,
            };
            match used {
                Ok(commands) => {
                    for command in commands {
                        self.deliver(Ok(command)).await;
                    }
                }
                Err(unusable) => self.refuse(unusable, topic).await,
            }
        }
    }

    /// The commands a message makes, in order (none while odometry has not moved enough).
    async fn take(&mut self, topic: Topic, payload: &[u8]) -> Result<Vec<Command>, Unusable> {
        let session = &self.session;
        let graph = |batch: Option<Batch>| {
            batch
                .map(|batch| Command::ApplyBatch {
                    session: session.clone(),
                    batch,
                    wait: false,
                })
                .into_iter()
                .collect()
        };
        let fusion = |feed: Feed| -> Vec<Command> {
            feed.batches
                .into_iter()
                .map(|messages| Command::Fusion {
                    session: session.clone(),
                    messages,
                })
                .collect()
        };
        Ok(match (topic, &mut self.feeder) {
            (Topic::Odometry, feeder) => {
                let odometry: Odometry = cdr_codec::decode(payload, ODOMETRY.name)?;
                let (commands, keyframes) = match feeder {
                    Feeder::Graph(keyframer) => {
                        let batch = keyframer.on_odometry(&odometry)?;
                        let keyframe = batch.as_ref().and(keyframer.last_keyframe());
                        (graph(batch), keyframe.into_iter().collect())
                    }
                    Feeder::Window(feed) => {
                        let feed = feed.on_odometry(&odometry)?;
                        let keyframes = feed.keyframes.clone();
                        (fusion(feed), keyframes)
                    }
                };
                if let Some(tf) = &self.tf {
                    let header = &odometry.header;
                    tf.on_odometry(header.stamp, &header.frame_id, &keyframes)
                        .await;
                }
                commands
            }
            (Topic::Prior, feeder) => {
                let prior: PoseWithCovarianceStamped =
                    cdr_codec::decode(payload, POSE_WITH_COVARIANCE_STAMPED.name)?;
                match feeder {
                    Feeder::Graph(keyframer) => graph(Some(keyframer.on_prior(&prior)?)),
                    Feeder::Window(feed) => fusion(feed.on_prior(&prior)?),
                }
            }
            (Topic::Imu, Feeder::Window(feed)) => {
                let imu: Imu = cdr_codec::decode(payload, IMU.name)?;
                let feed = feed.on_imu(&imu)?;
                if let (Some(tf), false) = (&self.tf, feed.keyframes.is_empty()) {
                    tf.on_keyframes(&feed.keyframes).await;
                }
                fusion(feed)
            }
            // A pose graph's binding subscribes to no IMU (`Ros2Binding::check_kind`).
            (Topic::Imu, Feeder::Graph(_)) => Vec::new(),
        })
    }

    async fn refuse(&self, unusable: Unusable, topic: Topic) {
        let refused = self.refused.fetch_add(1, Ordering::Relaxed) + 1;
        tracing::debug!(session = self.session, "ROS message refused: {unusable}");
        let error = ServiceError::bad_request(
            "ros2_bad_message",
            topic.field(),
            format!("{unusable} ({refused} ROS message(s) refused in this binding)"),
        );
        self.deliver(Err(error)).await;
    }

    /// As any transport's message: executed, a rejection on the session's error stream.
    async fn deliver(&self, decoded: Result<Command, ServiceError>) {
        let delivery = Delivery::decoded(&self.session, decoded);
        if let Err(e) = self.service.deliver_decoded(&self.caller, delivery).await {
            tracing::debug!(session = self.session, "ROS input without a session: {e}");
        }
    }
}
