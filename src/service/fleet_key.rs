//! The fleet's shared secret, and what instances prove with it.
//!
//! A fleet's instances trust each other with placement, with forwarded requests and with the
//! callers those requests act for; anyone who can reach the zenoh network can declare a
//! liveliness token under `<p>/@fleet/` and answer `info` with a URL of its own. So every
//! instance holds the same secret key (`fleet.secret_file`, at least 32 bytes) and proves with
//! it, as an HMAC-SHA256 over a fresh challenge, that it belongs:
//! - its `info` answer is signed over the asker's nonce and the exact bytes of the answer
//!   ([`Purpose::Info`]): an instance takes another into placement, the rpc gateway's election
//!   and the merged session lists only once that proof holds;
//! - a command forwarded over zenoh is signed with a timestamp and nonce ([`Purpose::Rpc`]),
//!   refused by the owner unless fresh and never seen before, and the owner's answer is signed
//!   over the same nonce ([`Purpose::RpcReply`]);
//! - an HTTP request forwarded to the owner carries no bearer token or cookie: the forwarding
//!   instance asserts the caller it authenticated, signed with a timestamp and nonce over the
//!   method, path and caller ([`Purpose::Caller`]).
//!
//! Every signed message names its purpose and frames each part with its length, so a proof
//! made for one message can never be read as the proof of another. Verification is ring's
//! constant-time comparison.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Mutex;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use ring::hmac;
use ring::rand::{SecureRandom, SystemRandom};

/// The shortest secret accepted: 256 bits, as HMAC-SHA256's key.
pub const MIN_SECRET_BYTES: usize = 32;
/// How far a signed timestamp may be from this instance's clock.
pub const FRESHNESS: Duration = Duration::from_secs(30);

/// What a proof is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Purpose {
    Info,
    Rpc,
    RpcReply,
    Caller,
}

impl Purpose {
    fn label(self) -> &'static [u8] {
        match self {
            Purpose::Info => b"factord-fleet-info-v1",
            Purpose::Rpc => b"factord-fleet-rpc-v1",
            Purpose::RpcReply => b"factord-fleet-rpc-reply-v1",
            Purpose::Caller => b"factord-fleet-caller-v1",
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum FleetKeyError {
    #[error("fleet secret file {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error(
        "fleet secret file {path} holds {len} bytes; at least {MIN_SECRET_BYTES} are needed \
         (e.g. `head -c 48 /dev/urandom | base64 > {path}`)"
    )]
    TooShort { path: String, len: usize },
}

/// Why a signed message was refused.
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
pub enum ProofError {
    #[error("no fleet proof")]
    Missing,
    #[error("a malformed fleet proof")]
    Malformed,
    #[error("a fleet proof that does not verify (not signed with this fleet's secret)")]
    Invalid,
    #[error("a fleet proof {0} s away from this instance's clock (allowed: 30 s)")]
    Stale(u64),
    #[error("a fleet proof seen before (a replay)")]
    Replayed,
}

/// The secret, and the nonces of fresh signed messages already accepted.
pub struct FleetKey {
    key: hmac::Key,
    random: SystemRandom,
    seen: Mutex<HashMap<String, u64>>,
}

impl std::fmt::Debug for FleetKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FleetKey(..)")
    }
}

/// A timestamped, nonced proof as it travels: `<unix seconds>.<nonce hex>.<hmac hex>`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Stamp {
    pub seconds: u64,
    pub nonce: String,
    pub proof: String,
}

impl Stamp {
    pub fn encode(&self) -> String {
        format!("{}.{}.{}", self.seconds, self.nonce, self.proof)
    }

    pub fn decode(text: &str) -> Result<Self, ProofError> {
        let mut parts = text.trim().splitn(3, '.');
        let (Some(seconds), Some(nonce), Some(proof)) = (parts.next(), parts.next(), parts.next())
        else {
            return Err(ProofError::Malformed);
        };
        let seconds = seconds.parse().map_err(|_| ProofError::Malformed)?;
        let hexadecimal = |s: &str| !s.is_empty() && s.len() <= 128 && hex::decode(s).is_ok();
        if !hexadecimal(nonce) || !hexadecimal(proof) {
            return Err(ProofError::Malformed);
        }
        Ok(Self {
            seconds,
            nonce: nonce.into(),
            proof: proof.into(),
        })
    }
}

fn now_seconds() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

impl FleetKey {
    /// The secret in the file at `path` (surrounding whitespace ignored).
    pub fn from_file(path: &Path) -> Result<Self, FleetKeyError> {
        let shown = path.display().to_string();
        let bytes = std::fs::read(path).map_err(|source| FleetKeyError::Read {
            path: shown.clone(),
            source,
        })?;
        let secret = bytes.trim_ascii();
        if secret.len() < MIN_SECRET_BYTES {
            return Err(FleetKeyError::TooShort {
                path: shown,
                len: secret.len(),
            });
        }
        Ok(Self::new(secret))
    }

    pub fn new(secret: &[u8]) -> Self {
        Self {
            key: hmac::Key::new(hmac::HMAC_SHA256, secret),
            random: SystemRandom::new(),
            seen: Mutex::new(HashMap::new()),
        }
    }

    /// A fresh random nonce, in hex.
    pub fn nonce(&self) -> String {
        let mut bytes = [0u8; 16];
        // The system's random source failing leaves no way to prove anything: a bug or a
        // broken kernel, not an input.
        self.random
            .fill(&mut bytes)
            .expect("the system random source works");
        hex::encode(bytes)
    }

    fn message(purpose: Purpose, parts: &[&[u8]]) -> Vec<u8> {
        let mut message = Vec::with_capacity(64 + parts.iter().map(|p| p.len() + 8).sum::<usize>());
        for part in std::iter::once(purpose.label()).chain(parts.iter().copied()) {
            message.extend_from_slice(&(part.len() as u64).to_be_bytes());
            message.extend_from_slice(part);
        }
        message
    }

    /// The proof of `parts` for `purpose`, in hex.
    pub fn sign(&self, purpose: Purpose, parts: &[&[u8]]) -> String {
        hex::encode(hmac::sign(&self.key, &Self::message(purpose, parts)).as_ref())
    }

    /// Whether `proof` (hex) is this fleet's proof of `parts` for `purpose`.
    pub fn verify(&self, purpose: Purpose, parts: &[&[u8]], proof: &str) -> Result<(), ProofError> {
        let tag = hex::decode(proof).map_err(|_| ProofError::Malformed)?;
        hmac::verify(&self.key, &Self::message(purpose, parts), &tag)
            .map_err(|_| ProofError::Invalid)
    }

    /// A stamp for `parts`: now, a fresh nonce, and the proof over both and the parts.
    pub fn stamp(&self, purpose: Purpose, parts: &[&[u8]]) -> Stamp {
        let (seconds, nonce) = (now_seconds(), self.nonce());
        let proof = self.sign(
            purpose,
            &Self::stamped(&seconds.to_be_bytes(), &nonce, parts),
        );
        Stamp {
            seconds,
            nonce,
            proof,
        }
    }

    fn stamped<'a>(seconds: &'a [u8], nonce: &'a str, parts: &[&'a [u8]]) -> Vec<&'a [u8]> {
        let mut all = vec![seconds, nonce.as_bytes()];
        all.extend_from_slice(parts);
        all
    }

    /// Accepts `stamp` over `parts` once: it must verify, be within [`FRESHNESS`] of this
    /// clock, and its nonce must not have been accepted before (nonces are remembered for as
    /// long as their stamps stay fresh, so a replay is refused either way).
    pub fn accept_once(
        &self,
        purpose: Purpose,
        parts: &[&[u8]],
        stamp: &Stamp,
    ) -> Result<(), ProofError> {
        let seconds = stamp.seconds.to_be_bytes();
        self.verify(
            purpose,
            &Self::stamped(&seconds, &stamp.nonce, parts),
            &stamp.proof,
        )?;
        let now = now_seconds();
        let skew = now.abs_diff(stamp.seconds);
        if skew > FRESHNESS.as_secs() {
            return Err(ProofError::Stale(skew));
        }
        let mut seen = self.seen.lock().unwrap_or_else(|p| p.into_inner());
        let horizon = now.saturating_sub(2 * FRESHNESS.as_secs());
        seen.retain(|_, &mut at| at >= horizon);
        if seen.insert(stamp.nonce.clone(), stamp.seconds).is_some() {
            return Err(ProofError::Replayed);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(secret: &str) -> FleetKey {
        FleetKey::new(secret.as_bytes())
    }

    #[test]
    fn a_proof_verifies_only_for_its_key_purpose_and_parts() {
        let k = key("a fleet secret of at least thirty-two bytes");
        let proof = k.sign(Purpose::Info, &[b"nonce", b"body"]);
        assert_eq!(
            k.verify(Purpose::Info, &[b"nonce", b"body"], &proof),
            Ok(())
        );
        let refused = Err(ProofError::Invalid);
        assert_eq!(
            k.verify(Purpose::Rpc, &[b"nonce", b"body"], &proof),
            refused
        );
        assert_eq!(
            k.verify(Purpose::Info, &[b"nonce", b"bodz"], &proof),
            refused
        );
        // Framing: moving bytes from one part to the next is another message.
        assert_eq!(
            k.verify(Purpose::Info, &[b"nonceb", b"ody"], &proof),
            refused
        );
        let other = key("another fleet secret of at least thirty-two bytes");
        assert_eq!(
            other.verify(Purpose::Info, &[b"nonce", b"body"], &proof),
            refused
        );
        assert_eq!(
            k.verify(Purpose::Info, &[b"nonce", b"body"], "zz"),
            Err(ProofError::Malformed)
        );
    }

    #[test]
    fn a_stamp_is_accepted_once_and_only_while_fresh() {
        let k = key("a fleet secret of at least thirty-two bytes");
        let stamp = k.stamp(Purpose::Rpc, &[b"payload"]);
        let decoded = Stamp::decode(&stamp.encode()).unwrap();
        assert_eq!(decoded, stamp);
        assert_eq!(k.accept_once(Purpose::Rpc, &[b"payload"], &decoded), Ok(()));
        assert_eq!(
            k.accept_once(Purpose::Rpc, &[b"payload"], &decoded),
            Err(ProofError::Replayed)
        );
        let other = k.stamp(Purpose::Rpc, &[b"payload"]);
        assert_eq!(
            k.accept_once(Purpose::Rpc, &[b"another payload"], &other),
            Err(ProofError::Invalid)
        );
        // A stamp from a minute ago, signed properly, is stale.
        let seconds = now_seconds() - 60;
        let nonce = k.nonce();
        let proof = k.sign(
            Purpose::Rpc,
            &FleetKey::stamped(&seconds.to_be_bytes(), &nonce, &[b"payload"]),
        );
        let old = Stamp {
            seconds,
            nonce,
            proof,
        };
        assert!(matches!(
            k.accept_once(Purpose::Rpc, &[b"payload"], &old),
            Err(ProofError::Stale(60..=61))
        ));
        assert_eq!(Stamp::decode("1.zz.00"), Err(ProofError::Malformed));
        assert_eq!(Stamp::decode("nope"), Err(ProofError::Malformed));
    }

    #[test]
    fn a_short_secret_file_is_refused() {
        let dir = std::env::temp_dir().join(format!("factord-fleet-key-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("secret");
        std::fs::write(&path, "too short\n").unwrap();
        assert!(matches!(
            FleetKey::from_file(&path),
            Err(FleetKeyError::TooShort { len: 9, .. })
        ));
        std::fs::write(&path, format!("{}\n", "x".repeat(32))).unwrap();
        assert!(FleetKey::from_file(&path).is_ok());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
