//! `factord health`: whether a running server answers, for container health checks.
//!
//! Asks `GET /v1/health` (open without a token) and wants `200` with `"status": "ok"`; with a
//! token it also asks `GET /metrics`, which needs one, so a token the server refuses is reported
//! too (a valid token that is not an operator's gets 403 there, and counts as accepted). Both routes are answered even when the server is at its connection limit (its reserve
//! connections), so a busy server is not reported unhealthy. Exit codes as Docker's
//! `HEALTHCHECK` reads them: 0 healthy, 1 unhealthy with a one-line reason on stderr (Docker
//! reserves 2; clap still exits with 2 on bad arguments).
//!
//! The requests go through hyper's client (the one the server's fleet forwarding uses) on a
//! runtime of one thread, within one deadline for the whole check.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

#[derive(clap::Args)]
pub struct HealthArgs {
    /// The server's HTTP address (plain http://; a path after the address is a prefix the
    /// routes are under)
    #[arg(long, env = "FACTORD_URL", default_value = "http://127.0.0.1:8080")]
    url: String,
    /// A file holding the bearer token: the token alone, or a tokens file as `serve
    /// --tokens-file` reads it (`label token` per line; the first token is used). Defaults to
    /// the server's own FACTORD_TOKENS_FILE, so inside its container `factord health` uses it.
    #[arg(long, env = "FACTORD_TOKENS_FILE")]
    token_file: Option<PathBuf>,
    /// The bearer token, when there is no --token-file (prefer the environment variable: a flag
    /// shows in the process list)
    #[arg(long, env = "FACTORD_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// How long the whole check may take, in milliseconds
    #[arg(long, env = "FACTORD_HEALTH_TIMEOUT_MS", default_value_t = 3000)]
    timeout_ms: u64,
}

/// Why the server is not healthy (each a one-line reason).
#[derive(Debug, thiserror::Error)]
enum Unhealthy {
    #[error("--url {url}: {reason}")]
    Url { url: String, reason: &'static str },
    #[error("token file {}: {reason}", path.display())]
    TokenFile { path: PathBuf, reason: String },
    #[error("cannot connect to {addr}: {reason}")]
    Connect { addr: String, reason: String },
    #[error("GET {path} on {addr}: no complete answer within {timeout_ms} ms")]
    Timeout {
        addr: String,
        path: String,
        timeout_ms: u64,
    },
    #[error("GET {path} on {addr}: {reason}")]
    Io {
        addr: String,
        path: String,
        reason: String,
    },
    #[error("GET {path} on {addr}: not an HTTP answer ({reason})")]
    Malformed {
        addr: String,
        path: String,
        reason: String,
    },
    #[error("GET {path} answered {status}: {message}")]
    Status {
        path: String,
        status: u16,
        message: String,
    },
    #[error("the server reports status `{0}`")]
    NotOk(String),
    #[error("the token was refused (GET /metrics answered 401: {0})")]
    TokenRefused(String),
}

/// Largest answer read (health and metrics are a few kilobytes).
const MAX_ANSWER_BYTES: usize = 1 << 20;

pub fn run(args: HealthArgs) -> ExitCode {
    match check(&args) {
        Ok(line) => {
            println!("{line}");
            ExitCode::SUCCESS
        }
        Err(reason) => {
            eprintln!("unhealthy: {reason}");
            ExitCode::FAILURE
        }
    }
}

/// The check; `Ok` holds the line printed for a healthy server.
fn check(args: &HealthArgs) -> Result<String, Unhealthy> {
    let deadline = Instant::now() + Duration::from_millis(args.timeout_ms.max(1));
    let target = Target::parse(&args.url)?;
    let token = match (&args.token_file, &args.token) {
        (Some(path), _) => Some(token_from_file(path)?),
        (None, Some(token)) => Some(token.trim().to_string()),
        (None, None) => None,
    };
    let client = Client {
        target: &target,
        token: token.as_deref(),
        deadline,
        timeout_ms: args.timeout_ms,
    };
    let health = client.get("/v1/health")?;
    if health.status != 200 {
        return Err(client.status_error("/v1/health", &health));
    }
    let body: serde_json::Value =
        serde_json::from_slice(&health.body).map_err(|e| Unhealthy::Malformed {
            addr: target.authority.clone(),
            path: "/v1/health".into(),
            reason: format!("body is not JSON: {e}"),
        })?;
    let status = body["status"].as_str().unwrap_or("(none)");
    if status != "ok" {
        return Err(Unhealthy::NotOk(status.to_string()));
    }
    let mut line = format!(
        "healthy: factord {} at {}, {} session(s), {} queued",
        body["version"].as_str().unwrap_or("?"),
        target.authority,
        body["sessions"],
        body["queued"]
    );
    if token.is_some() {
        let metrics = client.get("/metrics")?;
        match metrics.status {
            200 => line.push_str(", token accepted"),
            // Valid, but not an operator's: /metrics is withheld from tenants.
            403 => line.push_str(", token accepted (not an operator: /metrics withheld)"),
            401 => return Err(Unhealthy::TokenRefused(error_message(&metrics.body))),
            _ => return Err(client.status_error("/metrics", &metrics)),
        }
    }
    Ok(line)
}

/// The first token of a file: a bare token, or the last word of the first `label token` line
/// (blank lines and `#` comments skipped), as `serve --tokens-file` reads it.
fn token_from_file(path: &Path) -> Result<String, Unhealthy> {
    let text = std::fs::read_to_string(path).map_err(|e| Unhealthy::TokenFile {
        path: path.into(),
        reason: e.to_string(),
    })?;
    text.lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .and_then(|l| l.split_whitespace().last())
        .map(str::to_string)
        .ok_or_else(|| Unhealthy::TokenFile {
            path: path.into(),
            reason: "holds no token".into(),
        })
}

/// Where the server is: `host:port` as given (for `Host`) and the path prefix.
#[derive(Debug, PartialEq)]
struct Target {
    authority: String,
    prefix: String,
}

impl Target {
    fn parse(url: &str) -> Result<Self, Unhealthy> {
        let bad = |reason| Unhealthy::Url {
            url: url.to_string(),
            reason,
        };
        let rest = match url.split_once("://") {
            Some(("http", rest)) => rest,
            Some(("https", _)) => {
                return Err(bad(
                    "https is not spoken here: give the server's plain HTTP address",
                ))
            }
            Some(_) => return Err(bad("expected http://host:port")),
            None => url,
        };
        let (authority, path) = match rest.find('/') {
            Some(at) => rest.split_at(at),
            None => (rest, ""),
        };
        if authority.is_empty() || authority.contains('@') {
            return Err(bad("expected http://host:port"));
        }
        let has_port = match authority.rfind(']') {
            Some(close) => authority[close..].contains(':'),
            None => authority.contains(':'),
        };
        let authority = if has_port {
            authority.to_string()
        } else {
            format!("{authority}:80")
        };
        Ok(Self {
            authority,
            prefix: path.trim_end_matches('/').to_string(),
        })
    }
}

struct Client<'a> {
    target: &'a Target,
    token: Option<&'a str>,
    deadline: Instant,
    timeout_ms: u64,
}

/// An HTTP answer: status and body.
#[derive(Debug)]
struct Answer {
    status: u16,
    body: Vec<u8>,
}

impl Client<'_> {
    fn remaining(&self, path: &str) -> Result<Duration, Unhealthy> {
        let left = self.deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(self.timeout(path));
        }
        Ok(left)
    }

    fn timeout(&self, path: &str) -> Unhealthy {
        Unhealthy::Timeout {
            addr: self.target.authority.clone(),
            path: path.into(),
            timeout_ms: self.timeout_ms,
        }
    }

    fn get(&self, path: &str) -> Result<Answer, Unhealthy> {
        let io = |reason: String| Unhealthy::Io {
            addr: self.target.authority.clone(),
            path: path.into(),
            reason,
        };
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| io(format!("no runtime: {e}")))?;
        let left = self.remaining(path)?;
        runtime.block_on(async {
            tokio::time::timeout(left, self.fetch(path))
                .await
                .unwrap_or_else(|_| Err(self.timeout(path)))
        })
    }

    async fn fetch(&self, path: &str) -> Result<Answer, Unhealthy> {
        use axum::body::Body;
        use axum::http::{header, Request};
        let client =
            hyper_util::client::legacy::Client::builder(hyper_util::rt::TokioExecutor::new())
                .build_http::<Body>();
        let uri = format!(
            "http://{}{}{path}",
            self.target.authority, self.target.prefix
        );
        let mut request = Request::get(&uri).header(
            header::USER_AGENT,
            concat!("factord-health/", env!("CARGO_PKG_VERSION")),
        );
        if let Some(token) = self.token {
            request = request.header(header::AUTHORIZATION, format!("Bearer {token}"));
        }
        let request = request.body(Body::empty()).map_err(|e| Unhealthy::Url {
            url: uri.clone(),
            reason: if e.is::<axum::http::uri::InvalidUri>() {
                "not a valid address"
            } else {
                "not a valid request"
            },
        })?;
        let response = client.request(request).await.map_err(|e| {
            let reason = error_chain(&e);
            if e.is_connect() {
                Unhealthy::Connect {
                    addr: self.target.authority.clone(),
                    reason,
                }
            } else {
                Unhealthy::Malformed {
                    addr: self.target.authority.clone(),
                    path: path.into(),
                    reason,
                }
            }
        })?;
        let status = response.status().as_u16();
        let body = axum::body::to_bytes(Body::new(response.into_body()), MAX_ANSWER_BYTES)
            .await
            .map_err(|e| Unhealthy::Io {
                addr: self.target.authority.clone(),
                path: path.into(),
                reason: error_chain(&e),
            })?;
        Ok(Answer {
            status,
            body: body.to_vec(),
        })
    }

    fn status_error(&self, path: &str, answer: &Answer) -> Unhealthy {
        Unhealthy::Status {
            path: path.into(),
            status: answer.status,
            message: error_message(&answer.body),
        }
    }
}

/// The message of a factord error body (`{"error": {"message"}}`), else the body's first line.
fn error_message(body: &[u8]) -> String {
    if let Ok(v) = serde_json::from_slice::<serde_json::Value>(body) {
        if let Some(m) = v["error"]["message"].as_str() {
            return m.to_string();
        }
    }
    let text = String::from_utf8_lossy(body);
    match text.lines().next().map(str::trim) {
        Some(line) if !line.is_empty() => line.chars().take(200).collect(),
        _ => "(empty body)".into(),
    }
}

/// An error and its sources, on one line (hyper's own message is only the outermost).
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(inner) = source {
        text.push_str(": ");
        text.push_str(&inner.to_string());
        source = inner.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_give_host_port_and_prefix() {
        let t = Target::parse("http://factord-1:8080").unwrap();
        assert_eq!(
            (t.authority.as_str(), t.prefix.as_str()),
            ("factord-1:8080", "")
        );
        let t = Target::parse("http://[::1]:9000/base/").unwrap();
        assert_eq!(
            (t.authority.as_str(), t.prefix.as_str()),
            ("[::1]:9000", "/base")
        );
        assert_eq!(
            Target::parse("example.org").unwrap().authority,
            "example.org:80"
        );
        assert_eq!(Target::parse("http://[::1]").unwrap().authority, "[::1]:80");
        assert!(Target::parse("https://x:1").is_err());
        assert!(Target::parse("ftp://x:1").is_err());
        assert!(Target::parse("http://user@x:1").is_err());
    }

    #[test]
    fn token_files_give_their_first_token() {
        let dir = std::env::temp_dir().join(format!("factord-health-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("tokens");
        std::fs::write(&file, "# ops\n\nrobots  abcdefghijklmnop1234\nother x\n").unwrap();
        assert_eq!(token_from_file(&file).unwrap(), "abcdefghijklmnop1234");
        std::fs::write(&file, "  bare-token-of-sixteen  \n").unwrap();
        assert_eq!(token_from_file(&file).unwrap(), "bare-token-of-sixteen");
        std::fs::write(&file, "# only a comment\n").unwrap();
        assert!(token_from_file(&file).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn error_bodies_give_their_message() {
        let body =
            br#"{"error":{"code":"unauthorized","message":"the bearer token is not valid"}}"#;
        assert_eq!(error_message(body), "the bearer token is not valid");
        assert_eq!(error_message(b"plain\nmore"), "plain");
        assert_eq!(error_message(b""), "(empty body)");
    }
}
