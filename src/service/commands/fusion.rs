//! `fusion`: IMU samples, keyframes, relative poses and priors for a `sliding_window` session.

use crate::api::fusion::{FusionAck, FusionBatch};
use crate::api::{Fusion, ServiceError};
use crate::service::{off_async, Caller, Service};

impl Service {
    pub(super) async fn fusion(
        &self,
        caller: &Caller,
        request: Fusion,
    ) -> Result<FusionAck, ServiceError> {
        let session = self.writable_as(caller, &request.session)?;
        let batch = FusionBatch {
            messages: request.messages,
        };
        // A keyframe's optimisation takes about a millisecond: off the async threads.
        off_async("fusion update", move || session.apply_fusion(batch)).await
    }
}
