//! Flags that more than one command takes, declared once each: a group is a `clap::Args` struct
//! that a command flattens in where its flags stand in its help. Where commands word a flag
//! differently, the command rewords it (`mut_arg`); its name, type, value name and parsing stay
//! here. Also `serve`'s access control, limits and TLS.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Result};

use mrptv::protocol::Encoding;
use mrptv::rerun_log::RerunSink;
use mrptv::server::{self, ServerOptions};
use mrptv::tls::{CertificateOrigin, CertificateSource, ServerTls};
use mrptv_engine::synth::ScenarioSpec;
use mrptv_engine::PipelineConfig;

/// `--config`: a TOML processing config.
#[derive(clap::Args)]
pub struct ConfigFile {
    /// TOML config [default: REC/mrptv.toml if present, else built-in defaults].
    #[arg(long)]
    pub config: Option<PathBuf>,
}

impl ConfigFile {
    /// The file `--config` names, else the recording's own `REC/mrptv.toml` where it has one.
    pub fn or_in_recording(&self, rec: &Path) -> Option<PathBuf> {
        let suggested = rec.join("mrptv.toml");
        match &self.config {
            Some(path) => Some(path.clone()),
            None if suggested.is_file() => Some(suggested),
            None => None,
        }
    }
}

/// `--method` and `--depth-range`: the base config's choices and the measurement volume.
#[derive(clap::Args, Clone)]
pub struct ConfigChoices {
    /// Use the published method's choices (no mrptv improvements) as the base config.
    #[arg(long)]
    pub method: bool,
    /// The measurement volume's depths, metres along the cameras' common viewing direction:
    /// NEAR..FAR (FAR may be inf) [default: every depth both cameras see].
    #[arg(long, value_name = "NEAR..FAR")]
    pub depth_range: Option<DepthRange>,
}

impl ConfigChoices {
    /// `config` as these flags change it: with `--method` the published method's choices
    /// (keeping `config`'s scale parameters), then the `--depth-range` volume.
    pub fn apply(self, config: PipelineConfig) -> PipelineConfig {
        let mut config = if self.method {
            method_config(&config)
        } else {
            config
        };
        DepthRange::apply(self.depth_range, &mut config);
        config
    }
}

/// The published method's choices, keeping a scenario's scale parameters (M, H, contrast).
fn method_config(base: &PipelineConfig) -> PipelineConfig {
    let mut c = PipelineConfig::method();
    c.velocity.half_window_frames = base.velocity.half_window_frames;
    c.link.box_half_side_px = base.link.box_half_side_px;
    c.detect.contrast_c = base.detect.contrast_c;
    c
}

/// `--rerun` and `--rerun-images-every`: where a run is logged to Rerun, and how often with
/// its images.
#[derive(clap::Args)]
pub struct RerunArgs {
    /// Log the run to Rerun: file:RUN.rrd, connect (a viewer on this machine) or
    /// connect:URL. Repeat for several.
    #[arg(long, value_name = "SINK")]
    pub rerun: Vec<RerunSink>,
    /// With --rerun: log the camera images every N frames (0: never).
    #[arg(long, default_value_t = 10, value_name = "N")]
    pub rerun_images_every: u64,
}

/// `--frames`, `--particles` and `--seed` of a synthetic scenario.
#[derive(clap::Args)]
pub struct SceneSize {
    /// Number of frames [default: the scenario's].
    #[arg(long)]
    frames: Option<usize>,
    /// Number of particles in the domain [default: the scenario's].
    #[arg(long)]
    particles: Option<usize>,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

impl SceneSize {
    /// Frames and particles: as given, else the scenario's.
    pub fn of(&self, spec: &ScenarioSpec) -> Result<(usize, usize)> {
        let frames = self.frames.unwrap_or(spec.default_frames);
        let particles = self.particles.unwrap_or(spec.default_particles);
        if frames == 0 {
            bail!("--frames must be at least 1");
        }
        Ok((frames, particles))
    }
}

/// `--encoding`: how images travel as a headset sends them.
#[derive(clap::Args)]
pub struct WireEncoding {
    /// Image encoding on the wire: raw8, png (the recording's files, sent as they are) or sparse
    /// (particles exact, background coarse: what a headset's Wi-Fi carries).
    #[arg(long, default_value = "raw8")]
    pub encoding: Encoding,
}

/// `--url`: the server endpoint a headset client (`replay`, `hl2ss`) streams to.
#[derive(clap::Args)]
pub struct IngestUrl {
    #[arg(long, default_value = "ws://127.0.0.1:8770/v1/ingest")]
    pub url: String,
}

/// The ingest secret a headset client (`replay`, `hl2ss`) presents.
#[derive(clap::Args)]
pub struct IngestSecret {
    /// The server's ingest secret (see `serve --ingest-secret`).
    #[arg(
        long,
        env = "MRPTV_INGEST_SECRET",
        hide_env_values = true,
        value_name = "SECRET"
    )]
    pub secret: Option<String>,
}

/// `--ca-cert`: what a client trusts beyond the public web roots.
#[derive(clap::Args)]
pub struct CaCert {
    /// For wss:// URLs: also trust the certificates in this PEM file (e.g. a server's
    /// self-signed cert.pem); the public web roots are always trusted.
    #[arg(long, value_name = "PEM")]
    ca_cert: Option<PathBuf>,
}

impl CaCert {
    /// A client TLS configuration for wss:// URLs that also trusts the `--ca-cert` certificates.
    pub fn client_tls(&self) -> Result<Option<Arc<rustls::ClientConfig>>> {
        Ok(match &self.ca_cert {
            Some(path) => Some(mrptv::tls::client_config(Some(path))?),
            None => None,
        })
    }
}

/// `--watch-secret`: the secret viewers present (`serve` asks it, `hl2ss` presents it).
#[derive(clap::Args)]
pub struct WatchSecret {
    /// Secret viewers (the observer page: ?token=SECRET) and /v1/sessions must present.
    #[arg(
        long,
        env = "MRPTV_WATCH_SECRET",
        hide_env_values = true,
        value_name = "SECRET"
    )]
    pub watch_secret: Option<String>,
}

/// `--headsets`: how many headsets stream at once (`replay`, `load`).
#[derive(clap::Args)]
pub struct Headsets {
    /// Headsets streaming at once.
    #[arg(long, default_value_t = 1)]
    headsets: usize,
}

impl Headsets {
    pub fn count(&self) -> Result<usize> {
        if self.headsets == 0 {
            bail!("--headsets must be at least 1");
        }
        Ok(self.headsets)
    }
}

/// `--json`: a machine-readable summary instead of text.
#[derive(clap::Args)]
pub struct JsonOutput {
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Access control and limits of `serve` (defaults: `ServerOptions::default()`).
#[derive(clap::Args)]
#[command(next_help_heading = "Access and limits")]
pub struct GuardArgs {
    /// Secret headsets must present (Authorization: Bearer, or ?token=). Prefer the environment
    /// variable: command lines are visible to other users of this machine.
    #[arg(
        long,
        env = "MRPTV_INGEST_SECRET",
        hide_env_values = true,
        value_name = "SECRET"
    )]
    pub ingest_secret: Option<String>,
    #[command(flatten)]
    pub watch_secret: WatchSecret,
    /// Connections open at once; more are closed on accept.
    #[arg(long, default_value_t = ServerOptions::default().max_connections, value_name = "N")]
    max_connections: usize,
    /// Live sessions at once.
    #[arg(long, default_value_t = ServerOptions::default().max_sessions, value_name = "N")]
    max_sessions: usize,
    /// Viewers per session.
    #[arg(long, default_value_t = ServerOptions::default().max_viewers_per_session, value_name = "N")]
    max_viewers: usize,
    /// Largest image width or height, pixels.
    #[arg(long, default_value_t = ServerOptions::default().max_image_side, value_name = "PIXELS")]
    max_image_size: u32,
    /// Frames per second a session takes (bursts of one second's worth pass); 0: no limit.
    #[arg(long, default_value_t = ServerOptions::default().max_frame_rate_hz, value_name = "HZ")]
    max_frame_rate: f64,
    /// Largest WebSocket message, MiB (a raw8 stereo frame of 640x480 is 0.6 MiB).
    #[arg(long, default_value_t = ServerOptions::default().max_message_bytes >> 20, value_name = "MIB")]
    max_message_mib: usize,
    /// Seconds a client has for its TLS handshake, its HTTP request, and a headset its hello.
    #[arg(long, default_value_t = ServerOptions::default().handshake_timeout.as_secs_f64(), value_name = "S")]
    handshake_timeout: f64,
    /// Seconds of silence (not even a pong to the server's pings) before a connection is closed.
    #[arg(long, default_value_t = ServerOptions::default().idle_timeout.as_secs_f64(), value_name = "S")]
    idle_timeout: f64,
}

impl GuardArgs {
    pub fn apply(self, options: &mut ServerOptions) -> Result<()> {
        let seconds = |what: &str, s: f64| {
            if s.is_finite() && s > 0.0 && s < 1e6 {
                Ok(std::time::Duration::from_secs_f64(s))
            } else {
                bail!("--{what} must be a positive number of seconds, not {s}")
            }
        };
        if !(self.max_frame_rate.is_finite() && self.max_frame_rate >= 0.0) {
            bail!(
                "--max-frame-rate must be 0 (no limit) or a positive rate, not {}",
                self.max_frame_rate
            );
        }
        if self.max_message_mib == 0 || self.max_message_mib > 1024 {
            bail!(
                "--max-message-mib must be 1 to 1024, not {}",
                self.max_message_mib
            );
        }
        options.access = server::access::AccessControl::new(
            self.ingest_secret.as_deref(),
            self.watch_secret.watch_secret.as_deref(),
        )?;
        options.max_connections = self.max_connections;
        options.max_sessions = self.max_sessions;
        options.max_viewers_per_session = self.max_viewers;
        options.max_image_side = self.max_image_size;
        options.max_frame_rate_hz = self.max_frame_rate;
        options.max_message_bytes = self.max_message_mib << 20;
        options.handshake_timeout = seconds("handshake-timeout", self.handshake_timeout)?;
        options.idle_timeout = seconds("idle-timeout", self.idle_timeout)?;
        Ok(())
    }
}

/// `serve`'s HTTPS/WSS flags.
#[derive(clap::Args)]
pub struct TlsArgs {
    /// Serve HTTPS and WSS only (browsers give WebXR to secure pages only). Without
    /// --tls-cert: a self-signed certificate, generated once and kept in --tls-dir.
    #[arg(long)]
    tls: bool,
    /// PEM certificate chain to serve (implies --tls; needs --tls-key).
    #[arg(long, value_name = "PEM", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long, value_name = "PEM", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Where the self-signed certificate is kept [default: ~/.local/share/mrptv/tls].
    #[arg(long, value_name = "DIR")]
    tls_dir: Option<PathBuf>,
    /// Extra host name or IP address the self-signed certificate must cover (repeatable);
    /// localhost, this host's name and addresses are always in it.
    #[arg(long, value_name = "NAME")]
    tls_name: Vec<String>,
}

impl TlsArgs {
    /// Where the server's certificate comes from; `None`: plain HTTP.
    pub fn source(self, bind: SocketAddr) -> Option<CertificateSource> {
        match (self.tls_cert, self.tls_key) {
            (Some(cert), Some(key)) => Some(CertificateSource::Files { cert, key }),
            _ if self.tls => Some(CertificateSource::SelfSigned {
                dir: self
                    .tls_dir
                    .unwrap_or_else(mrptv::tls::default_self_signed_dir),
                names: certificate_names(bind, self.tls_name),
            }),
            _ => None,
        }
    }
}

/// Loads or makes the certificate and says which one is served, with its fingerprint.
pub fn setup_tls(source: &CertificateSource) -> Result<ServerTls> {
    let tls = mrptv::tls::server_tls(source)?;
    match tls.origin {
        CertificateOrigin::Given => {
            println!("TLS: certificate {}", tls.cert_path.display())
        }
        CertificateOrigin::Generated => println!(
            "TLS: generated a self-signed certificate {} for {}",
            tls.cert_path.display(),
            tls.names.join(", ")
        ),
        CertificateOrigin::Reused => println!(
            "TLS: self-signed certificate {} (for {})",
            tls.cert_path.display(),
            tls.names.join(", ")
        ),
    }
    println!("  SHA-256 fingerprint {}", tls.fingerprint);
    if tls.origin != CertificateOrigin::Given {
        println!(
            "  browsers warn about a self-signed certificate: check that the fingerprint they show matches, then accept it"
        );
    }
    Ok(tls)
}

/// Names a self-signed certificate covers: loopback, this host's name (and its mDNS `.local`
/// name), the bind address or, for a wildcard bind, the address of the default route's
/// interface, and what the user adds.
fn certificate_names(bind: SocketAddr, extra: Vec<String>) -> Vec<String> {
    let mut names = vec!["localhost".to_string(), "127.0.0.1".into(), "::1".into()];
    if let Some(host) = host_name() {
        names.push(format!("{host}.local"));
        names.push(host);
    }
    if bind.ip().is_unspecified() {
        names.extend(lan_address().map(|ip| ip.to_string()));
    } else {
        names.push(bind.ip().to_string());
    }
    names.extend(extra);
    let mut seen = std::collections::BTreeSet::new();
    names.retain(|n| seen.insert(n.clone()));
    names
}

fn host_name() -> Option<String> {
    let name = std::fs::read_to_string("/etc/hostname")
        .ok()
        .or_else(|| std::env::var("COMPUTERNAME").ok())?;
    let name = name.trim();
    (!name.is_empty() && name != "localhost").then(|| name.to_string())
}

/// The address other devices on the network most likely reach this host at: the source address
/// of the default route (a UDP "connect" sends nothing).
pub fn lan_address() -> Option<std::net::IpAddr> {
    let socket = std::net::UdpSocket::bind("0.0.0.0:0").ok()?;
    socket.connect("192.0.2.1:9").ok()?;
    let ip = socket.local_addr().ok()?.ip();
    (!ip.is_unspecified() && !ip.is_loopback()).then_some(ip)
}

/// `--depth-range NEAR..FAR`: the measurement volume's depth range, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthRange {
    pub near_m: f64,
    pub far_m: f64,
}

impl std::str::FromStr for DepthRange {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let usage = || format!("'{s}' is not NEAR..FAR in metres (e.g. 0.3..0.8, or 0.5..inf)");
        let (near, far) = s.split_once("..").ok_or_else(usage)?;
        let near_m: f64 = near.trim().parse().map_err(|_| usage())?;
        let far_m: f64 = far.trim().parse().map_err(|_| usage())?;
        if !(near_m.is_finite() && near_m > 0.0 && far_m > near_m) {
            return Err(format!("{s}: need 0 < NEAR < FAR (metres)"));
        }
        Ok(Self { near_m, far_m })
    }
}

impl DepthRange {
    /// An explicit volume replaces the stereo search from the views' overlap, and the method's
    /// image-fraction K.
    pub fn apply(range: Option<Self>, config: &mut mrptv_engine::PipelineConfig) {
        if let Some(r) = range {
            config.stereo.depth_range_m = Some([r.near_m, r.far_m]);
            config.stereo.disparity_range_fraction = None;
        }
    }
}
