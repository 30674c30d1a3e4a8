//! Decoding requests: JSON bodies (objects only, the offending field named on failure, item
//! lists bounded before they are decoded) and query parameters, into [`ServiceError`]s.

use super::error::{ErrorKind, ServiceError};

/// Parses a JSON request body (an object), naming the offending field on failure.
///
/// A valid body is decoded once, straight; only one that fails is decoded again through
/// `serde_path_to_error` to name the field (tracking the path of every value costs about a
/// fifth of the decoding, measured on 1000-factor batches).
pub fn parse_json<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, ServiceError> {
    require_object(bytes)?;
    match serde_json::from_slice(bytes) {
        Ok(value) => Ok(value),
        Err(_) => parse_json_located(bytes),
    }
}

/// The body starts with `{` (serde would also fill a struct from an array by position; the API
/// only speaks objects).
fn require_object(bytes: &[u8]) -> Result<(), ServiceError> {
    match bytes.iter().find(|b| !b.is_ascii_whitespace()) {
        Some(b'{') => {}
        Some(_) => {
            return Err(ServiceError::new(
                ErrorKind::BadRequest,
                "malformed_json",
                "the body must be a JSON object",
            ))
        }
        None => {
            return Err(ServiceError::new(
                ErrorKind::BadRequest,
                "malformed_json",
                "the body is empty",
            ))
        }
    }
    Ok(())
}

/// Decodes `bytes` tracking the path of every value, so an error names its field.
fn parse_json_located<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, ServiceError> {
    let de = &mut serde_json::Deserializer::from_slice(bytes);
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let code = if inner.is_syntax() || inner.is_eof() {
            "malformed_json"
        } else {
            "invalid_field"
        };
        let err = ServiceError::new(
            ErrorKind::BadRequest,
            code,
            format!("invalid JSON body: {inner}"),
        );
        if path == "." {
            err
        } else {
            err.at(path)
        }
    })
}

/// Parses a JSON request body whose item lists (see `session::wire_list`) hold at most
/// `max_items` items in all: 413 `batch_too_large` at the first item beyond, before the rest of
/// the body is decoded.
pub fn parse_json_within<T: serde::de::DeserializeOwned>(
    bytes: &[u8],
    max_items: usize,
) -> Result<T, ServiceError> {
    use crate::api::wire_list::{check_shape, decode_within, ShapeError};
    match check_shape(bytes, max_items) {
        Ok(()) => {}
        Err(e @ ShapeError::TooManyItems { .. }) => {
            return Err(ServiceError::too_large("batch_too_large", e.to_string()).at("batch"))
        }
        Err(e @ ShapeError::TooManyNumbers) => {
            return Err(ServiceError::too_large("list_too_long", e.to_string()).at("body"))
        }
    }
    require_object(bytes)?;
    // The common case first, as `parse_json` does; the budget starts afresh for the second
    // decoding of a failing body.
    if let Ok(Ok(value)) = decode_within(max_items, || serde_json::from_slice::<T>(bytes)) {
        return Ok(value);
    }
    let mut beyond = None;
    let decoded = decode_within(max_items, || {
        parse_json_located::<T>(bytes).inspect_err(|e| beyond = e.body.field.clone())
    });
    decoded.unwrap_or_else(|exceeded| {
        let error = ServiceError::too_large(
            "batch_too_large",
            format!(
                "the request has more than {} items (variables, factors, removals, fixes, \
                 guesses, messages; limits.max_batch_items): split it",
                exceeded.limit
            ),
        );
        Err(error.at(beyond.unwrap_or_else(|| "batch".into())))
    })
}

/// Parses query parameters (`a=1&b=2`; zenoh selectors separate them with `;`), naming the
/// offending parameter on failure.
pub fn parse_query<T: serde::de::DeserializeOwned>(query: &str) -> Result<T, ServiceError> {
    let query = query.replace(';', "&");
    let de = serde_urlencoded::Deserializer::new(form_urlencoded::parse(query.as_bytes()));
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let message = e.into_inner().to_string();
        // An unknown parameter is named in the message, not the path.
        let field = match message.split('`').nth(1) {
            Some(name) if path == "." => name.to_string(),
            _ => path,
        };
        ServiceError::bad_request(
            "invalid_query",
            field,
            format!("invalid query parameter: {message}"),
        )
    })
}
