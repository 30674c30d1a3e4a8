//! A request forwarded to another fleet member carries no credential of the caller's.
//!
//! The instance a client reached has authenticated it (bearer token or login cookie). When it
//! forwards the request to the session's owner, a bearer token sent on would reach whatever
//! host the membership names, so with a fleet secret (`service::fleet_key`) the token and
//! cookies are removed, and the forwarder asserts the caller it authenticated instead:
//! `Factord-Forwarded-Caller` (`trusted`, `anonymous` or `principal:<label in hex>`) and
//! `Factord-Forwarded-Proof`, a stamp (time, nonce, HMAC) over the method, the path with its
//! query and the caller. The owner accepts the assertion once, while fresh, and the request
//! then runs as that caller; a request with a proof that does not verify is refused 401, never
//! read as unauthenticated. On a trusted network (no secret) the request goes on as before,
//! token included, and the owner checks the token again.

use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderName, HeaderValue, Method};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use crate::api::ErrorKind;
use crate::service::fleet::Fleet;
use crate::service::fleet_key::{Purpose, Stamp};
use crate::service::{Caller, Service, ServiceError};

pub const FORWARDED_CALLER: HeaderName = HeaderName::from_static("factord-forwarded-caller");
pub const FORWARDED_PROOF: HeaderName = HeaderName::from_static("factord-forwarded-proof");

/// The caller a fleet member asserted for a forwarded request, verified here (only
/// [`accept_asserted`] puts it in a request).
#[derive(Clone, Debug)]
pub struct AssertedCaller(pub Caller);

impl AssertedCaller {
    /// The token label it acts for, where tokens are in force: a principal's; none for an
    /// anonymous caller (a trusted one exists only where no tokens are, and is not one here).
    pub fn principal(&self) -> Option<Arc<str>> {
        match &self.0 {
            Caller::Principal(label) => Some(Arc::clone(label)),
            Caller::Trusted | Caller::Anonymous => None,
        }
    }
}

fn encode(caller: &Caller) -> String {
    match caller {
        Caller::Trusted => "trusted".into(),
        Caller::Anonymous => "anonymous".into(),
        Caller::Principal(label) => format!("principal:{}", hex::encode(label.as_bytes())),
    }
}

fn decode(text: &str) -> Option<Caller> {
    match text {
        "trusted" => Some(Caller::Trusted),
        "anonymous" => Some(Caller::Anonymous),
        _ => {
            let label = hex::decode(text.strip_prefix("principal:")?).ok()?;
            Some(Caller::Principal(String::from_utf8(label).ok()?.into()))
        }
    }
}

/// Readies the `headers` of a request forwarded to another member: with a fleet secret, the
/// caller's credentials are replaced by the signed assertion of `caller` for `method` on
/// `target` (the path and query the owner will see).
pub(super) fn assert_caller(
    fleet: &Fleet,
    headers: &mut HeaderMap,
    method: &Method,
    target: &str,
    caller: &Caller,
) {
    let Some(key) = fleet.key() else {
        return;
    };
    headers.remove(header::AUTHORIZATION);
    headers.remove(header::COOKIE);
    let asserted = encode(caller);
    let stamp = key.stamp(
        Purpose::Caller,
        &[
            method.as_str().as_bytes(),
            target.as_bytes(),
            asserted.as_bytes(),
        ],
    );
    // Both are hex, digits and a few ASCII punctuation marks: always valid header values.
    if let (Ok(caller), Ok(proof)) = (
        HeaderValue::from_str(&asserted),
        HeaderValue::from_str(&stamp.encode()),
    ) {
        headers.insert(FORWARDED_CALLER, caller);
        headers.insert(FORWARDED_PROOF, proof);
    }
}

fn refused(message: String) -> Response {
    super::HttpError::from(
        ServiceError::new(ErrorKind::Unauthorized, "fleet_proof_invalid", message)
            .at("factord-forwarded-proof"),
    )
    .into_response()
}

/// The middleware: a request with `Factord-Forwarded-Proof` runs as the caller it asserts
/// when the proof holds, and is refused otherwise.
pub async fn accept_asserted(
    State(service): State<Arc<Service>>,
    mut request: Request,
    next: Next,
) -> Response {
    let Some(proof) = request.headers().get(FORWARDED_PROOF) else {
        return next.run(request).await;
    };
    let Some(key) = service.fleet().and_then(|f| f.key()) else {
        return refused("this instance has no fleet secret to check an asserted caller".into());
    };
    let stamp = match proof.to_str().map(Stamp::decode) {
        Ok(Ok(stamp)) => stamp,
        _ => return refused("a malformed fleet proof".into()),
    };
    let asserted = request
        .headers()
        .get(FORWARDED_CALLER)
        .and_then(|v| v.to_str().ok())
        .unwrap_or_default()
        .to_string();
    let target = request
        .uri()
        .path_and_query()
        .map_or("/", |p| p.as_str())
        .to_string();
    let method = request.method().as_str().to_string();
    let parts = [method.as_bytes(), target.as_bytes(), asserted.as_bytes()];
    if let Err(e) = key.accept_once(Purpose::Caller, &parts, &stamp) {
        tracing::warn!("fleet: a forwarded request refused: {e}");
        return refused(e.to_string());
    }
    let Some(caller) = decode(&asserted) else {
        return refused("a malformed asserted caller".into());
    };
    request.extensions_mut().insert(AssertedCaller(caller));
    next.run(request).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn callers_round_trip_through_their_header_form() {
        for caller in [
            Caller::Trusted,
            Caller::Anonymous,
            Caller::Principal("tenant a; with \"odd\" bytes ✓".into()),
        ] {
            let text = encode(&caller);
            assert!(HeaderValue::from_str(&text).is_ok(), "{text}");
            assert_eq!(decode(&text), Some(caller));
        }
        assert_eq!(decode("principal:zz"), None);
        assert_eq!(decode("root"), None);
    }
}
