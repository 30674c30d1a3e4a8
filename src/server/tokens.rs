//! Which bearer tokens HTTP requires, from `auth` and `FACTORD_TOKENS`, and the start-time
//! refusals that keep an open back-end off the network.

use std::net::SocketAddr;
use std::sync::Arc;

use super::{AuthConfig, ServeError};
use crate::transport::http::auth::Tokens;

/// The tokens HTTP requires, if any: always beyond loopback, and wherever configured.
pub(super) fn tokens_for(
    auth: &AuthConfig,
    addr: &SocketAddr,
) -> Result<Option<Arc<Tokens>>, ServeError> {
    let mut tokens = match &auth.tokens_file {
        Some(file) => Tokens::load(file).map_err(|e| ServeError::Auth(e.to_string()))?,
        None => Tokens::default(),
    };
    if let Ok(list) = std::env::var("FACTORD_TOKENS") {
        tokens
            .extend_from_list(&list)
            .map_err(|e| ServeError::Auth(e.to_string()))?;
    }
    let beyond_loopback = !addr.ip().is_loopback();
    match auth.required {
        Some(false) if beyond_loopback => Err(ServeError::Auth(format!(
            "HTTP listens on {addr}, beyond loopback: tokens cannot be switched off there"
        ))),
        Some(false) => Ok(None),
        required if (required == Some(true) || beyond_loopback) && tokens.is_empty() => {
            Err(ServeError::Auth(format!(
                "HTTP on {addr} requires bearer tokens: give --tokens-file or FACTORD_TOKENS"
            )))
        }
        _ if tokens.is_empty() => Ok(None),
        _ => {
            if let Some(operators) = &auth.operators {
                tokens
                    .set_operators(operators)
                    .map_err(|e| ServeError::Auth(e.to_string()))?;
            }
            if tokens.metrics_closed() {
                tracing::warn!(
                    "GET /metrics answers 403 to every token: several token labels are \
                     configured and auth.operators (--operators) names none of them"
                );
            }
            tracing::info!("HTTP requires bearer tokens ({} configured)", tokens.len());
            Ok(Some(Arc::new(tokens)))
        }
    }
}
