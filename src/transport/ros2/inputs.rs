//! The binding's subscriptions: odometry and absolute poses, in the order they arrive, decoded
//! from CDR, turned into batches by the [`Keyframer`] and executed as any client's batch.
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
    Odometry, PoseWithCovarianceStamped, ODOMETRY, POSE_WITH_COVARIANCE_STAMPED,
};
use super::tf::TfBroadcaster;
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

pub(super) struct Inputs {
    pub service: Arc<Service>,
    pub caller: Arc<Caller>,
    pub session: String,
    pub keyframer: Keyframer,
    pub odometry: Samples,
    pub priors: Option<Samples>,
    /// Told of every odometry message used and every keyframe made (`map → odom` on `/tf`).
    pub tf: Option<Arc<TfBroadcaster>>,
    /// Messages refused so far (reported with each refusal).
    pub refused: Arc<AtomicU64>,
}

impl Inputs {
    /// Takes messages until both subscriptions end (the binding is dropped).
    pub async fn run(mut self) {
        loop {
            let (sample, is_odometry) = match &self.priors {
                Some(priors) => tokio::select! {
                    s = self.odometry.recv_async() => (s, true),
                    s = priors.recv_async() => (s, false),
                },
                None => (self.odometry.recv_async().await, true),
            };
            let Ok(sample) = sample else { return };
            let payload = sample.payload().to_bytes();
            // rmw_zenoh always attaches one; a sample without (a plain zenoh put) is taken, one
            // with something else is not from rmw_zenoh and is refused.
            let attachment = sample
                .attachment()
                .map(|a| Attachment::decode(&a.to_bytes()));
            let batch = match (attachment, is_odometry) {
                (Some(Err(e)), _) => Err(e.into()),
                (_, true) => self.odometry_batch(&payload).await,
                (_, false) => self.prior_batch(&payload),
            };
            match batch {
                Ok(Some(batch)) => self.apply(batch).await,
                Ok(None) => {}
                Err(unusable) => self.refuse(unusable, is_odometry).await,
            }
        }
    }

    async fn odometry_batch(&mut self, payload: &[u8]) -> Result<Option<Batch>, Unusable> {
        let odometry: Odometry = cdr_codec::decode(payload, ODOMETRY.name)?;
        let batch = self.keyframer.on_odometry(&odometry)?;
        if let Some(tf) = &self.tf {
            let keyframe = batch.as_ref().and(self.keyframer.last_keyframe());
            let header = &odometry.header;
            tf.on_odometry(header.stamp, &header.frame_id, keyframe)
                .await;
        }
        Ok(batch)
    }

    fn prior_batch(&mut self, payload: &[u8]) -> Result<Option<Batch>, Unusable> {
        let prior: PoseWithCovarianceStamped =
            cdr_codec::decode(payload, POSE_WITH_COVARIANCE_STAMPED.name)?;
        Ok(Some(self.keyframer.on_prior(&prior)?))
    }

    async fn apply(&self, batch: Batch) {
        let command = Command::ApplyBatch {
            session: self.session.clone(),
            batch,
            wait: false,
        };
        self.deliver(Ok(command)).await;
    }

    async fn refuse(&self, unusable: Unusable, is_odometry: bool) {
        let refused = self.refused.fetch_add(1, Ordering::Relaxed) + 1;
        let topic = match is_odometry {
            true => "ros2.odometry_topic",
            false => "ros2.prior_topic",
        };
        tracing::debug!(session = self.session, "ROS message refused: {unusable}");
        let error = ServiceError::bad_request(
            "ros2_bad_message",
            topic,
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
