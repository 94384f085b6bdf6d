//! `mrptv hl2ss --holograms`: the live vectors drawn back into the wearer's view through the
//! message queue of hl2ss's Unity plugin ("remote Unity scene", TCP 3816).
//!
//! Wire format (hl2ss `viewer/hl2ss_rus.py`, `RemoteUnityScene.cs`): each command is
//! `<u32 id, u32 size>` then `size` bytes, little-endian; the plugin answers every command with
//! one u32, in order (create: the new object's key; others: 1 done, 0 refused). Commands between
//! "begin display list" and "end display list" are applied together, in one Unity frame.
//!
//! A fixed pool of cylinders is created once; each update moves, colours and shows as many as
//! there are vectors and hides the rest, in one display list, at most `rate_hz` times a second.
//! Unity's world is left-handed: hl2ss's (right-handed, y up, z toward the wearer) point
//! (x, y, z) is Unity's (x, y, -z). The vectors are asked of the server in its `"unity"`
//! convention, which is exactly that.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use nalgebra::{UnitQuaternion, Vector3};

use crate::protocol::{DecodedBatch, FieldMessage};

pub const MESSAGE_QUEUE_PORT: u16 = 3816;
pub const CREATE_PRIMITIVE: u32 = 0;
pub const SET_ACTIVE: u32 = 1;
pub const SET_WORLD_TRANSFORM: u32 = 2;
pub const SET_COLOR: u32 = 4;
pub const REMOVE: u32 = 16;
pub const BEGIN_DISPLAY_LIST: u32 = 18;
pub const END_DISPLAY_LIST: u32 = 19;
/// Unity's `PrimitiveType.Cylinder`: 2 units tall along its local y, 1 across.
pub const CYLINDER: u32 = 2;

/// One command, framed.
pub(crate) fn message(id: u32, data: &[u8]) -> Vec<u8> {
    let mut m = Vec::with_capacity(8 + data.len());
    m.extend_from_slice(&id.to_le_bytes());
    m.extend_from_slice(&(data.len() as u32).to_le_bytes());
    m.extend_from_slice(data);
    m
}

/// Shows (`true`) or hides the primitive `key`.
fn set_active(key: u32, active: bool) -> Vec<u8> {
    message(
        SET_ACTIVE,
        &[key.to_le_bytes(), u32::from(active).to_le_bytes()].concat(),
    )
}

fn words(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// `set world transform`: key, position, rotation (x, y, z, w), scale, in Unity's frame.
pub(crate) fn world_transform(
    key: u32,
    position: [f32; 3],
    rotation: [f32; 4],
    scale: [f32; 3],
) -> Vec<u8> {
    let mut data = key.to_le_bytes().to_vec();
    data.extend(words(&position));
    data.extend(words(&rotation));
    data.extend(words(&scale));
    message(SET_WORLD_TRANSFORM, &data)
}

/// An arrow of a vector as a Unity cylinder: centre, rotation taking +y along the vector, and
/// scale (`width` across, `length` long). Input and output in Unity's frame.
pub(crate) fn arrow_transform(
    position_m: [f32; 3],
    velocity_m_per_s: [f32; 3],
    seconds: f64,
    width_m: f64,
) -> ([f32; 3], [f32; 4], [f32; 3]) {
    let p = Vector3::from(position_m.map(f64::from));
    let v = Vector3::from(velocity_m_per_s.map(f64::from));
    let length = (v.norm() * seconds).max(1e-4);
    let centre = p + v * (seconds / 2.0);
    let rotation = UnitQuaternion::rotation_between(&Vector3::y(), &v).unwrap_or_else(|| {
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
    });
    let q = rotation.coords; // x, y, z, w
    (
        [centre.x as f32, centre.y as f32, centre.z as f32],
        [q[0] as f32, q[1] as f32, q[2] as f32, q[3] as f32],
        [width_m as f32, (length / 2.0) as f32, width_m as f32],
    )
}

#[derive(Debug, thiserror::Error)]
pub enum HologramError {
    #[error("hl2ss message queue at {addr}: {error}")]
    Io { addr: String, error: std::io::Error },
    #[error("hl2ss message queue refused {refused} of {sent} commands (is the Unity plugin app running?)")]
    Refused { refused: usize, sent: usize },
}

/// One arrow to draw, Unity's convention.
struct Arrow {
    position: [f32; 3],
    velocity: [f32; 3],
    opacity: f32,
}

/// What the holograms show.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum HologramContent {
    /// The newest frame's (causal) vectors.
    #[default]
    Vectors,
    /// The session's mean-flow field: an arrow per grid cell.
    Field,
}

/// The pool of arrows in the wearer's view.
pub struct Painter {
    stream: TcpStream,
    addr: String,
    keys: Vec<u32>,
    shown: usize,
    min_interval: Duration,
    last: Option<Instant>,
    /// Fixed from the first batch with vectors, like the observer page's legend.
    speed_max: Option<f64>,
    arrow_seconds: f64,
    /// Display lists sent, commands refused.
    pub updates: u64,
    pub refused: u64,
}

impl Painter {
    /// Connects and creates `arrows` hidden cylinders.
    pub fn connect(
        host: &str,
        port: u16,
        arrows: usize,
        rate_hz: f64,
    ) -> Result<Self, HologramError> {
        let addr = format!("{host}:{port}");
        let stream = TcpStream::connect(&addr).map_err(|error| HologramError::Io {
            addr: addr.clone(),
            error,
        })?;
        let _ = stream.set_nodelay(true);
        let _ = stream.set_read_timeout(Some(Duration::from_secs(10)));
        let _ = stream.set_write_timeout(Some(Duration::from_secs(10)));
        let mut painter = Self {
            stream,
            addr,
            keys: Vec::new(),
            shown: 0,
            min_interval: Duration::from_secs_f64(1.0 / rate_hz.max(0.1)),
            last: None,
            speed_max: None,
            arrow_seconds: 0.1,
            updates: 0,
            refused: 0,
        };
        let mut list = vec![message(BEGIN_DISPLAY_LIST, &[])];
        for _ in 0..arrows {
            list.push(message(CREATE_PRIMITIVE, &CYLINDER.to_le_bytes()));
        }
        list.push(message(END_DISPLAY_LIST, &[]));
        let answers = painter.send(&list)?;
        painter.keys = answers[1..=arrows].to_vec();
        // Hidden until there is something to show (whatever the plugin's default).
        let mut hide = vec![message(BEGIN_DISPLAY_LIST, &[])];
        for &key in &painter.keys {
            hide.push(set_active(key, false));
        }
        hide.push(message(END_DISPLAY_LIST, &[]));
        painter.send(&hide)?;
        Ok(painter)
    }

    /// Sends commands, reads one answer each.
    fn send(&mut self, commands: &[Vec<u8>]) -> Result<Vec<u32>, HologramError> {
        let io = |error| HologramError::Io {
            addr: self.addr.clone(),
            error,
        };
        self.stream.write_all(&commands.concat()).map_err(io)?;
        let mut answers = vec![0u8; 4 * commands.len()];
        self.stream
            .read_exact(&mut answers)
            .map_err(|error| HologramError::Io {
                addr: self.addr.clone(),
                error,
            })?;
        Ok(answers
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    /// Draws a batch unless the last update was under `1 / rate_hz` ago; `true` if drawn.
    pub(crate) fn paint(&mut self, batch: &DecodedBatch) -> Result<bool, HologramError> {
        let arrows: Vec<Arrow> = batch
            .vectors
            .iter()
            .map(|v| Arrow {
                position: v.position_m,
                velocity: v.velocity_m_per_s,
                opacity: 1.0,
            })
            .collect();
        self.paint_arrows(&arrows)
    }

    /// Draws a `field` message's cells (in Unity's convention): the mean velocity at each
    /// cell's centre, cells of fewer than `FIELD_FULL_SAMPLES` samples faded.
    pub(crate) fn paint_field(&mut self, field: &FieldMessage) -> Result<bool, HologramError> {
        let arrows: Vec<Arrow> = field
            .cells
            .iter()
            .map(|c| Arrow {
                position: [c[0] as f32, c[1] as f32, c[2] as f32],
                velocity: [c[4] as f32, c[5] as f32, c[6] as f32],
                opacity: if c[3] >= crate::rerun_log::FIELD_FULL_SAMPLES as f64 {
                    1.0
                } else {
                    0.35
                },
            })
            .collect();
        self.paint_arrows(&arrows)
    }

    fn paint_arrows(&mut self, arrows: &[Arrow]) -> Result<bool, HologramError> {
        let now = Instant::now();
        if self.last.is_some_and(|t| now - t < self.min_interval) {
            return Ok(false);
        }
        self.last = Some(now);
        let speeds: Vec<f64> = arrows
            .iter()
            .map(|a| Vector3::from(a.velocity.map(f64::from)).norm())
            .collect();
        if self.speed_max.is_none() && !speeds.is_empty() {
            let mut sorted = speeds.clone();
            sorted.sort_by(f64::total_cmp);
            let median = sorted[sorted.len() / 2].max(1e-6);
            self.speed_max = Some(crate::rerun_log::nice_ceiling(2.0 * median));
            // A median arrow 5 cm long: visible across a room, not in the way.
            self.arrow_seconds = 0.05 / median;
        }
        let speed_max = self.speed_max.unwrap_or(1.0);
        let mut list = vec![message(BEGIN_DISPLAY_LIST, &[])];
        let n = arrows.len().min(self.keys.len());
        for (i, (a, speed)) in arrows.iter().zip(&speeds).take(n).enumerate() {
            let key = self.keys[i];
            let (position, rotation, scale) =
                arrow_transform(a.position, a.velocity, self.arrow_seconds, 0.004);
            list.push(world_transform(key, position, rotation, scale));
            let [r, g, b] = crate::rerun_log::speed_color(*speed, speed_max);
            let rgba = [
                f32::from(r) / 255.0,
                f32::from(g) / 255.0,
                f32::from(b) / 255.0,
                a.opacity,
            ];
            list.push(message(
                SET_COLOR,
                &[key.to_le_bytes().to_vec(), words(&rgba)].concat(),
            ));
            if i >= self.shown {
                list.push(set_active(key, true));
            }
        }
        for &key in &self.keys[n..self.shown.max(n)] {
            list.push(set_active(key, false));
        }
        list.push(message(END_DISPLAY_LIST, &[]));
        let answers = self.send(&list)?;
        // The list's own begin and end are always accepted; what matters is the rest.
        let commands = &answers[1..answers.len() - 1];
        let refused = commands.iter().filter(|&&a| a == 0).count();
        self.refused += refused as u64;
        self.updates += 1;
        self.shown = n;
        if refused > 0 && refused == commands.len() {
            // The pool is gone (the Unity scene was reloaded): nothing drawn will show.
            return Err(HologramError::Refused {
                refused,
                sent: commands.len(),
            });
        }
        Ok(true)
    }

    /// Removes the pool (on the way out).
    pub fn remove_all(&mut self) -> Result<(), HologramError> {
        let list: Vec<Vec<u8>> = self
            .keys
            .iter()
            .map(|key| message(REMOVE, &key.to_le_bytes()))
            .collect();
        self.send(&list).map(|_| ())
    }
}

/// Follows the session of the headset named `client` as a viewer of the server (`watch_url`,
/// `/v1/watch`) and hands its causal batches to `painter` on its own thread (a batch arriving
/// while the previous one is being painted is skipped: the wearer sees the newest). Ends when
/// `stop` resolves; returns the painter with its counts.
pub async fn follow_and_paint(
    watch_url: String,
    secret: Option<String>,
    tls: Option<std::sync::Arc<rustls::ClientConfig>>,
    client: String,
    content: HologramContent,
    mut painter: Painter,
    stop: impl std::future::Future<Output = ()>,
) -> Result<Painter, String> {
    use futures_util::{SinkExt, StreamExt};
    use tokio_tungstenite::tungstenite::Message;

    let request = match crate::client::authorized_request(&watch_url, secret.as_deref()) {
        Ok(request) => request,
        Err(e) => {
            let _ = painter.remove_all();
            return Err(e.to_string());
        }
    };
    let connector = tls.map(tokio_tungstenite::Connector::Rustls);
    let (mut ws, _) = match tokio_tungstenite::connect_async_tls_with_config(
        request, None, true, connector,
    )
    .await
    {
        Ok(connected) => connected,
        Err(e) => {
            let _ = painter.remove_all();
            return Err(format!("watching {watch_url}: {e}"));
        }
    };
    enum Drawing {
        Batch(DecodedBatch),
        Field(Box<FieldMessage>),
    }
    let (batches, to_paint) = std::sync::mpsc::sync_channel::<Drawing>(1);
    let painting = std::thread::spawn(move || {
        let mut error = None;
        for drawing in to_paint {
            let painted = match &drawing {
                Drawing::Batch(batch) => painter.paint(batch),
                Drawing::Field(field) => painter.paint_field(field),
            };
            if let Err(e) = painted {
                error = Some(e.to_string());
                break;
            }
        }
        let _ = painter.remove_all();
        (painter, error)
    });
    let mut subscribed = false;
    let mut failure = None;
    tokio::pin!(stop);
    loop {
        tokio::select! {
            m = ws.next() => match m {
                Some(Ok(Message::Text(t))) => {
                    if subscribed {
                        if let (HologramContent::Field, Ok(crate::protocol::ServerMessage::Field(field))) =
                            (content, serde_json::from_str(t.as_str()))
                        {
                            // Skipped while the painter is busy: the next field is newer.
                            let _ = batches.try_send(Drawing::Field(field));
                        }
                        continue;
                    }
                    let Ok(crate::protocol::ServerMessage::Sessions { sessions }) =
                        serde_json::from_str(t.as_str())
                    else {
                        continue;
                    };
                    if let Some(s) = sessions.iter().find(|s| s.session.client == client) {
                        let subscribe = serde_json::json!({
                            "type": "subscribe", "session": s.session.id, "convention": "unity"
                        });
                        if let Err(e) = ws.send(Message::text(subscribe.to_string())).await {
                            failure = Some(e.to_string());
                            break;
                        }
                        subscribed = true;
                    }
                }
                Some(Ok(Message::Binary(b))) => {
                    if content != HologramContent::Vectors {
                        continue;
                    }
                    if let Ok(batch) = crate::protocol::decode_batch(&b) {
                        if batch.kind == crate::protocol::BatchKind::Causal
                            && batches.try_send(Drawing::Batch(batch)).is_err()
                        {
                            // The painter is busy with the previous one: this one is skipped.
                        }
                    }
                }
                Some(Ok(_)) => {}
                Some(Err(e)) => {
                    failure = Some(e.to_string());
                    break;
                }
                None => break,
            },
            _ = &mut stop => break,
        }
    }
    // The painter removes its arrows whatever ended the watch; its thread is waited for on a
    // blocking thread, not on the runtime's.
    drop(batches);
    let (painter, error) = tokio::task::spawn_blocking(move || painting.join())
        .await
        .map_err(|e| e.to_string())?
        .map_err(|_| "the hologram painter panicked".to_string())?;
    match failure.or(error) {
        Some(e) => Err(e),
        None => Ok(painter),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_arrow_points_along_its_vector_in_unitys_frame() {
        // Moving toward the wearer's right and away from them (+z in Unity).
        let (centre, q, scale) = arrow_transform([0.0, 1.0, 2.0], [0.3, 0.0, 0.4], 0.2, 0.01);
        let expected = [0.03, 1.0, 2.04];
        assert!(
            centre
                .iter()
                .zip(expected)
                .all(|(a, b)| (a - b).abs() < 1e-6),
            "{centre:?}"
        );
        let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            f64::from(q[3]),
            f64::from(q[0]),
            f64::from(q[1]),
            f64::from(q[2]),
        ));
        let axis = q * Vector3::y();
        assert!((axis - Vector3::new(0.6, 0.0, 0.8)).norm() < 1e-6, "{axis}");
        assert!((scale[1] - 0.05).abs() < 1e-6 && scale[0] == 0.01);
        // Straight down: the degenerate case of the shortest rotation.
        let (_, q, _) = arrow_transform([0.0; 3], [0.0, -1.0, 0.0], 0.1, 0.01);
        let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            f64::from(q[3]),
            f64::from(q[0]),
            f64::from(q[1]),
            f64::from(q[2]),
        ));
        assert!((q * Vector3::y() - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-6);
    }

    #[test]
    fn messages_are_framed_as_the_plugin_reads_them() {
        let m = world_transform(7, [1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0], [1.0; 3]);
        assert_eq!(&m[..8], &[2, 0, 0, 0, 44, 0, 0, 0]);
        assert_eq!(m.len(), 8 + 44);
        assert_eq!(
            message(BEGIN_DISPLAY_LIST, &[]),
            vec![18, 0, 0, 0, 0, 0, 0, 0]
        );
    }
}
