//! Who may connect: one secret for headsets (`/v1/ingest`), another for viewers (`/v1/watch`,
//! `/v1/sessions`), each optional. A client presents its secret as `Authorization: Bearer
//! SECRET` or, where it cannot set headers (a browser's WebSocket), as `?token=SECRET`.

use std::net::SocketAddr;

use axum::http::{header, HeaderMap};
use subtle::ConstantTimeEq;

/// What a connection asks to do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// A headset streaming frames.
    Ingest,
    /// A viewer receiving vectors, or a client listing sessions.
    Watch,
}

impl Role {
    fn what(self) -> &'static str {
        match self {
            Role::Ingest => "headsets (/v1/ingest): the ingest secret",
            Role::Watch => "viewers (/v1/watch, /v1/sessions): the watch secret",
        }
    }
}

/// A secret as kept in memory: its SHA-256, so comparing takes the same time whatever the
/// length or content of what a client presents.
#[derive(Clone)]
pub(crate) struct Secret([u8; 32]);

impl std::fmt::Debug for Secret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Secret(..)")
    }
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SecretError {
    #[error("the {0} secret is empty")]
    Empty(&'static str),
    #[error("the {0} secret has {1} characters; use at least {MIN_SECRET_CHARS} (e.g. `openssl rand -hex 16`)")]
    TooShort(&'static str, usize),
    #[error("the ingest and watch secrets are the same: a viewer could then stream as a headset")]
    Shared,
}

/// Short enough to type on a headset keyboard, long enough not to be guessed online.
pub(crate) const MIN_SECRET_CHARS: usize = 12;

fn digest(text: &str) -> [u8; 32] {
    let d = ring::digest::digest(&ring::digest::SHA256, text.as_bytes());
    let mut out = [0; 32];
    out.copy_from_slice(d.as_ref());
    out
}

impl Secret {
    fn new(role: &'static str, text: &str) -> Result<Self, SecretError> {
        let chars = text.chars().count();
        if chars == 0 {
            return Err(SecretError::Empty(role));
        }
        if chars < MIN_SECRET_CHARS {
            return Err(SecretError::TooShort(role, chars));
        }
        Ok(Self(digest(text)))
    }

    fn admits(&self, presented: &str) -> bool {
        bool::from(self.0.ct_eq(&digest(presented)))
    }
}

/// The server's secrets; `Default` is open to all.
#[derive(Debug, Clone, Default)]
pub struct AccessControl {
    ingest: Option<Secret>,
    watch: Option<Secret>,
}

impl AccessControl {
    pub fn new(ingest: Option<&str>, watch: Option<&str>) -> Result<Self, SecretError> {
        if let (Some(i), Some(w)) = (ingest, watch) {
            if bool::from(digest(i).ct_eq(&digest(w))) {
                return Err(SecretError::Shared);
            }
        }
        Ok(Self {
            ingest: ingest.map(|s| Secret::new("ingest", s)).transpose()?,
            watch: watch.map(|s| Secret::new("watch", s)).transpose()?,
        })
    }

    pub fn requires(&self, role: Role) -> bool {
        self.secret(role).is_some()
    }

    fn secret(&self, role: Role) -> Option<&Secret> {
        match role {
            Role::Ingest => self.ingest.as_ref(),
            Role::Watch => self.watch.as_ref(),
        }
    }

    /// `Ok` when the request may go on; otherwise what to tell the client.
    pub(crate) fn check(
        &self,
        role: Role,
        headers: &HeaderMap,
        token: Option<&str>,
    ) -> Result<(), String> {
        let Some(secret) = self.secret(role) else {
            return Ok(());
        };
        // The scheme name is case-insensitive (RFC 9110); the secret is compared exactly.
        let bearer = headers
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.split_once(' '))
            .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
            .map(|(_, secret)| secret);
        match bearer.or(token) {
            Some(presented) if secret.admits(presented) => Ok(()),
            Some(_) => Err(format!("wrong secret for {}", role.what())),
            None => Err(format!(
                "this server requires a secret for {}; send `Authorization: Bearer SECRET` or `?token=SECRET`",
                role.what()
            )),
        }
    }
}

/// What is exposed, said plainly, when the server listens beyond loopback: anyone who can reach
/// the port can stream or watch without secrets, and without TLS secrets and vectors cross the
/// network in clear.
pub fn exposure_warnings(bound: SocketAddr, access: &AccessControl, tls: bool) -> Vec<String> {
    if bound.ip().is_loopback() {
        return Vec::new();
    }
    let mut warnings = Vec::new();
    let open: Vec<&str> = [(Role::Ingest, "headsets"), (Role::Watch, "viewers")]
        .into_iter()
        .filter(|(role, _)| !access.requires(*role))
        .map(|(_, who)| who)
        .collect();
    if !open.is_empty() {
        warnings.push(format!(
            "listening on {bound}, beyond loopback, with no secret for {}: anyone who can reach this port may connect (set --ingest-secret / --watch-secret or MRPTV_INGEST_SECRET / MRPTV_WATCH_SECRET)",
            open.join(" or ")
        ));
    }
    if !tls {
        warnings.push(format!(
            "listening on {bound}, beyond loopback, without TLS: frames, vectors and secrets cross the network in clear (use --tls)"
        ));
    }
    warnings
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    fn bearer(secret: &str) -> HeaderMap {
        let mut h = HeaderMap::new();
        h.insert(
            header::AUTHORIZATION,
            HeaderValue::from_str(&format!("Bearer {secret}")).expect("header"),
        );
        h
    }

    #[test]
    fn each_role_takes_only_its_own_secret() {
        let access =
            AccessControl::new(Some("headset-secret-1"), Some("viewer-secret-22")).expect("valid");
        let none = HeaderMap::new();
        assert!(access
            .check(Role::Ingest, &bearer("headset-secret-1"), None)
            .is_ok());
        let mut lower = HeaderMap::new();
        lower.insert(
            header::AUTHORIZATION,
            HeaderValue::from_static("bearer headset-secret-1"),
        );
        assert!(access.check(Role::Ingest, &lower, None).is_ok());
        assert!(access
            .check(Role::Ingest, &bearer(" headset-secret-1"), None)
            .is_err());
        assert!(access
            .check(Role::Ingest, &none, Some("headset-secret-1"))
            .is_ok());
        assert!(access
            .check(Role::Watch, &none, Some("viewer-secret-22"))
            .is_ok());
        let wrong = access
            .check(Role::Watch, &none, Some("headset-secret-1"))
            .expect_err("the ingest secret does not open watch");
        assert!(wrong.contains("wrong secret"), "{wrong}");
        let missing = access
            .check(Role::Ingest, &none, None)
            .expect_err("no secret");
        assert!(missing.contains("Authorization: Bearer"), "{missing}");
        assert!(access
            .check(Role::Ingest, &bearer("headset-secret-"), None)
            .is_err());
        assert!(access
            .check(Role::Ingest, &bearer("headset-secret-12"), None)
            .is_err());
        // A wrong header is not rescued by a right token, nor the reverse: the header wins.
        assert!(access
            .check(
                Role::Ingest,
                &bearer("nope-nope-nope"),
                Some("headset-secret-1")
            )
            .is_err());
    }

    #[test]
    fn open_by_default_and_one_role_may_stay_open() {
        let none = HeaderMap::new();
        assert!(AccessControl::default()
            .check(Role::Ingest, &none, None)
            .is_ok());
        let watch_only = AccessControl::new(None, Some("viewer-secret-22")).expect("valid");
        assert!(watch_only.check(Role::Ingest, &none, None).is_ok());
        assert!(watch_only.check(Role::Watch, &none, None).is_err());
    }

    #[test]
    fn weak_or_shared_secrets_are_refused() {
        assert_eq!(
            AccessControl::new(Some(""), None).expect_err("empty"),
            SecretError::Empty("ingest")
        );
        assert!(matches!(
            AccessControl::new(None, Some("short")),
            Err(SecretError::TooShort("watch", 5))
        ));
        assert_eq!(
            AccessControl::new(Some("same-secret-123"), Some("same-secret-123"))
                .expect_err("shared"),
            SecretError::Shared
        );
    }

    #[test]
    fn exposure_is_warned_about_beyond_loopback_only() {
        let open = AccessControl::default();
        let loopback: SocketAddr = "127.0.0.1:8770".parse().expect("addr");
        let v6_loopback: SocketAddr = "[::1]:8770".parse().expect("addr");
        let lan: SocketAddr = "0.0.0.0:8770".parse().expect("addr");
        assert!(exposure_warnings(loopback, &open, false).is_empty());
        assert!(exposure_warnings(v6_loopback, &open, false).is_empty());
        let w = exposure_warnings(lan, &open, false);
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(w[0].contains("headsets or viewers"), "{w:?}");
        assert!(w[1].contains("without TLS"), "{w:?}");
        let guarded =
            AccessControl::new(Some("headset-secret-1"), Some("viewer-secret-22")).expect("ok");
        assert!(exposure_warnings(lan, &guarded, true).is_empty());
        let half = AccessControl::new(Some("headset-secret-1"), None).expect("ok");
        let w = exposure_warnings(lan, &half, true);
        assert_eq!(w.len(), 1);
        assert!(w[0].contains("no secret for viewers"), "{w:?}");
    }
}
