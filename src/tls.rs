//! TLS for `mrptv serve --tls` (browsers offer WebXR only to secure contexts, so a headset's
//! browser needs `https://`) and for clients of `wss://` servers (`mrptv replay`).
//!
//! Certificates come from the user (PEM files) or are generated once, self-signed, and kept in
//! a directory so their fingerprint stays the same across restarts: a browser that was told to
//! trust it once keeps trusting it.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use serde::{Deserialize, Serialize};

#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write {path}: {source}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Pem { path: PathBuf, message: String },
    #[error("certificate {cert} with key {key} refused: {source}")]
    Refused {
        cert: PathBuf,
        key: PathBuf,
        source: rustls::Error,
    },
    #[error("cannot generate a self-signed certificate: {0}")]
    Generate(#[from] rcgen::Error),
    #[error("TLS set-up: {0}")]
    Rustls(#[from] rustls::Error),
}

/// Where the server's certificate comes from.
#[derive(Debug, Clone)]
pub enum CertificateSource {
    /// The user's certificate chain and private key, PEM.
    Files { cert: PathBuf, key: PathBuf },
    /// A self-signed certificate for `names` (DNS names or IP addresses), kept in `dir` and
    /// reused while it covers `names` and is more than a week from expiry.
    SelfSigned { dir: PathBuf, names: Vec<String> },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CertificateOrigin {
    Given,
    Generated,
    Reused,
}

/// A ready server configuration and what to tell the user about it.
pub struct ServerTls {
    pub config: Arc<rustls::ServerConfig>,
    pub cert_path: PathBuf,
    /// SHA-256 of the leaf certificate (DER), as browsers show it: `AB:CD:...`.
    pub fingerprint: String,
    pub origin: CertificateOrigin,
    /// Names a self-signed certificate covers (empty for a given one).
    pub names: Vec<String>,
}

/// `$XDG_DATA_HOME/mrptv/tls`, else `~/.local/share/mrptv/tls`, else `./mrptv-tls`.
pub fn default_self_signed_dir() -> PathBuf {
    let base = std::env::var_os("XDG_DATA_HOME")
        .filter(|v| !v.is_empty())
        .map(PathBuf::from)
        .or_else(|| {
            std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".local").join("share"))
        });
    match base {
        Some(base) => base.join("mrptv").join("tls"),
        None => PathBuf::from("mrptv-tls"),
    }
}

fn provider() -> Arc<rustls::crypto::CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

pub(crate) fn fingerprint_sha256(der: &[u8]) -> String {
    ring::digest::digest(&ring::digest::SHA256, der)
        .as_ref()
        .iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(":")
}

fn read_certs(path: &Path) -> Result<Vec<CertificateDer<'static>>, TlsError> {
    let bytes = std::fs::read(path).map_err(|source| TlsError::Read {
        path: path.to_owned(),
        source,
    })?;
    let certs = CertificateDer::pem_slice_iter(&bytes)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| TlsError::Pem {
            path: path.to_owned(),
            message: format!("not a PEM certificate file ({e})"),
        })?;
    if certs.is_empty() {
        return Err(TlsError::Pem {
            path: path.to_owned(),
            message: "holds no PEM certificate (-----BEGIN CERTIFICATE-----)".into(),
        });
    }
    Ok(certs)
}

fn read_key(path: &Path) -> Result<PrivateKeyDer<'static>, TlsError> {
    let bytes = std::fs::read(path).map_err(|source| TlsError::Read {
        path: path.to_owned(),
        source,
    })?;
    PrivateKeyDer::from_pem_slice(&bytes).map_err(|e| TlsError::Pem {
        path: path.to_owned(),
        message: format!("holds no PEM private key (PKCS#8, PKCS#1 or SEC1): {e}"),
    })
}

fn server_config(cert: &Path, key: &Path) -> Result<(Arc<rustls::ServerConfig>, String), TlsError> {
    let certs = read_certs(cert)?;
    let private_key = read_key(key)?;
    let fingerprint = fingerprint_sha256(certs[0].as_ref());
    let mut config = rustls::ServerConfig::builder_with_provider(provider())
        .with_safe_default_protocol_versions()?
        .with_no_client_auth()
        .with_single_cert(certs, private_key)
        .map_err(|source| TlsError::Refused {
            cert: cert.to_owned(),
            key: key.to_owned(),
            source,
        })?;
    // The server speaks HTTP/1.1 only (WebSocket upgrades).
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok((Arc::new(config), fingerprint))
}

/// What a generated certificate was made for, kept beside it.
#[derive(Debug, Serialize, Deserialize)]
struct SelfSignedInfo {
    names: Vec<String>,
    not_after_unix: i64,
}

const SELF_SIGNED_DAYS: i64 = 397; // the longest validity browsers accept
const RENEW_BEFORE_DAYS: i64 = 7;

pub fn server_tls(source: &CertificateSource) -> Result<ServerTls, TlsError> {
    match source {
        CertificateSource::Files { cert, key } => {
            let (config, fingerprint) = server_config(cert, key)?;
            Ok(ServerTls {
                config,
                cert_path: cert.clone(),
                fingerprint,
                origin: CertificateOrigin::Given,
                names: Vec::new(),
            })
        }
        CertificateSource::SelfSigned { dir, names } => self_signed(dir, names),
    }
}

fn self_signed(dir: &Path, names: &[String]) -> Result<ServerTls, TlsError> {
    let cert = dir.join("cert.pem");
    let key = dir.join("key.pem");
    let info_path = dir.join("names.json");
    let now = time::OffsetDateTime::now_utc();
    let reusable = std::fs::read(&info_path)
        .ok()
        .and_then(|b| serde_json::from_slice::<SelfSignedInfo>(&b).ok())
        .filter(|info| {
            names.iter().all(|n| info.names.contains(n))
                && info.not_after_unix - now.unix_timestamp() > RENEW_BEFORE_DAYS * 86_400
        });
    if let Some(info) = reusable {
        if cert.is_file() && key.is_file() {
            let (config, fingerprint) = server_config(&cert, &key)?;
            return Ok(ServerTls {
                config,
                cert_path: cert,
                fingerprint,
                origin: CertificateOrigin::Reused,
                names: info.names,
            });
        }
    }
    let mut params = rcgen::CertificateParams::new(names.to_vec())?;
    params
        .distinguished_name
        .push(rcgen::DnType::CommonName, "mrptv self-signed");
    params.not_before = now - time::Duration::days(1);
    let not_after = now + time::Duration::days(SELF_SIGNED_DAYS);
    params.not_after = not_after;
    let key_pair = rcgen::KeyPair::generate()?;
    let generated = params.self_signed(&key_pair)?;
    let write = |path: &Path, text: &str, private: bool| -> Result<(), TlsError> {
        let failed = |source| TlsError::Write {
            path: path.to_owned(),
            source,
        };
        std::fs::create_dir_all(dir).map_err(failed)?;
        std::fs::write(path, text).map_err(failed)?;
        #[cfg(unix)]
        if private {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600))
                .map_err(failed)?;
        }
        #[cfg(not(unix))]
        let _ = private;
        Ok(())
    };
    write(&key, &key_pair.serialize_pem(), true)?;
    write(&cert, &generated.pem(), false)?;
    let info = SelfSignedInfo {
        names: names.to_vec(),
        not_after_unix: not_after.unix_timestamp(),
    };
    write(
        &info_path,
        &serde_json::to_string_pretty(&info).unwrap_or_default(),
        false,
    )?;
    let (config, fingerprint) = server_config(&cert, &key)?;
    Ok(ServerTls {
        config,
        cert_path: cert,
        fingerprint,
        origin: CertificateOrigin::Generated,
        names: names.to_vec(),
    })
}

/// A client configuration trusting the public web roots plus, if given, the certificates in
/// `extra_ca` (e.g. a server's self-signed `cert.pem`).
pub fn client_config(extra_ca: Option<&Path>) -> Result<Arc<rustls::ClientConfig>, TlsError> {
    let mut roots = rustls::RootCertStore {
        roots: webpki_roots::TLS_SERVER_ROOTS.to_vec(),
    };
    if let Some(path) = extra_ca {
        for cert in read_certs(path)? {
            roots.add(cert).map_err(|e| TlsError::Pem {
                path: path.to_owned(),
                message: format!("certificate refused as a trust anchor: {e}"),
            })?;
        }
    }
    let config = rustls::ClientConfig::builder_with_provider(provider())
        .with_safe_default_protocol_versions()?
        .with_root_certificates(roots)
        .with_no_client_auth();
    Ok(Arc::new(config))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_self_signed_certificate_is_kept_and_reused_until_the_names_change() {
        let dir = tempfile::tempdir().expect("tempdir");
        let names = vec!["localhost".to_string(), "127.0.0.1".to_string()];
        let first = server_tls(&CertificateSource::SelfSigned {
            dir: dir.path().into(),
            names: names.clone(),
        })
        .expect("generated");
        assert_eq!(first.origin, CertificateOrigin::Generated);
        assert_eq!(first.fingerprint.len(), 32 * 3 - 1);
        let again = server_tls(&CertificateSource::SelfSigned {
            dir: dir.path().into(),
            names: vec!["127.0.0.1".into()],
        })
        .expect("reused");
        assert_eq!(again.origin, CertificateOrigin::Reused);
        assert_eq!(again.fingerprint, first.fingerprint);
        let other = server_tls(&CertificateSource::SelfSigned {
            dir: dir.path().into(),
            names: vec!["mrptv.lan".into()],
        })
        .expect("regenerated");
        assert_eq!(other.origin, CertificateOrigin::Generated);
        assert_ne!(other.fingerprint, first.fingerprint);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(dir.path().join("key.pem"))
                .expect("key")
                .permissions()
                .mode();
            assert_eq!(mode & 0o077, 0, "private key readable by others");
        }
    }

    #[test]
    fn bad_certificate_files_are_named() {
        let dir = tempfile::tempdir().expect("tempdir");
        let garbage = dir.path().join("garbage.pem");
        std::fs::write(&garbage, "not a certificate").expect("write");
        let missing = dir.path().join("missing.pem");
        let message = |cert: &Path, key: &Path| {
            server_tls(&CertificateSource::Files {
                cert: cert.into(),
                key: key.into(),
            })
            .err()
            .expect("refused")
            .to_string()
        };
        let m = message(&missing, &garbage);
        assert!(m.contains("missing.pem"), "{m}");
        let m = message(&garbage, &garbage);
        assert!(
            m.contains("garbage.pem") && m.contains("no PEM certificate"),
            "{m}"
        );
        // A real certificate with another certificate's key.
        let a = server_tls(&CertificateSource::SelfSigned {
            dir: dir.path().join("a"),
            names: vec!["localhost".into()],
        })
        .expect("a");
        server_tls(&CertificateSource::SelfSigned {
            dir: dir.path().join("b"),
            names: vec!["localhost".into()],
        })
        .expect("b");
        let m = message(&a.cert_path, &dir.path().join("b").join("key.pem"));
        assert!(m.contains("refused"), "{m}");
        let ca = client_config(Some(&a.cert_path));
        assert!(ca.is_ok());
        assert!(client_config(Some(&garbage)).is_err());
    }
}
