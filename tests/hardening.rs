//! The server under hostile input, exhaustion and faults: secrets, limits, timeouts, every kind
//! of malformed message, peers that vanish mid-frame or stop reading, a Rerun sink that goes
//! away. Each test also asserts that a well-behaved session alongside is unaffected.

use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use mrptv::client::ReplayOptions;
use mrptv::protocol::{encode_frame, Encoding, ErrorCode, FrameMessage, ServerMessage};
use mrptv::rerun_log::{start_proxy, RerunOptions, RerunSink};
use mrptv::server::access::AccessControl;
use mrptv::server::ServerOptions;
use mrptv_engine::synth::Scenario;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::Message;

mod common;
use common::*;

const INGEST: &str = "headset-secret-0123";
const WATCH: &str = "viewer-secret-4567";

/// Connects with an `Authorization: Bearer` header; the HTTP refusal if the server refuses.
async fn connect_with(
    url: &str,
    secret: Option<&str>,
) -> Result<Socket, tokio_tungstenite::tungstenite::Error> {
    let mut request = url.into_client_request().expect("a request");
    if let Some(secret) = secret {
        request.headers_mut().insert(
            "authorization",
            format!("Bearer {secret}").parse().expect("header"),
        );
    }
    tokio_tungstenite::connect_async(request).await.map(|c| c.0)
}

/// The 401 and its protocol error, from a refused upgrade.
fn assert_unauthorized(result: Result<Socket, tokio_tungstenite::tungstenite::Error>) -> String {
    let Err(tokio_tungstenite::tungstenite::Error::Http(response)) = result else {
        panic!(
            "expected an HTTP refusal, got {:?}",
            result.map(|_| "a socket")
        );
    };
    assert_eq!(response.status(), 401);
    assert_eq!(
        response
            .headers()
            .get("www-authenticate")
            .and_then(|v| v.to_str().ok()),
        Some("Bearer")
    );
    let body = response.body().as_deref().expect("a body");
    match serde_json::from_slice::<ServerMessage>(body).expect("a protocol message") {
        ServerMessage::Error { code, message, .. } => {
            assert_eq!(code, ErrorCode::Unauthorized);
            message
        }
        other => panic!("{other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_endpoint_takes_only_its_own_secret() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Flume, 12);
    let server = TestServer::start(ServerOptions {
        access: AccessControl::new(Some(INGEST), Some(WATCH)).expect("secrets"),
        ..Default::default()
    })
    .await;

    let m = assert_unauthorized(connect_with(&server.ingest(), None).await);
    assert!(m.contains("requires a secret for headsets"), "{m}");
    let m = assert_unauthorized(connect_with(&server.ingest(), Some(WATCH)).await);
    assert!(m.contains("wrong secret"), "{m}");
    assert_unauthorized(connect_with(&server.watch(), Some(INGEST)).await);
    assert_unauthorized(connect_with(&server.watch(), None).await);
    let wrong_token = format!("{}?token=viewer-secret-4568", server.watch());
    assert_unauthorized(connect_with(&wrong_token, None).await);

    // The reference client with the ingest secret streams as usual.
    let report = replay(
        &rec,
        &ReplayOptions {
            secret: Some(INGEST.into()),
            ..replay_options(server.ingest(), &config)
        },
    )
    .await;
    assert_eq!(report.counters.map(|c| c.frames_processed), Some(12));

    // A viewer with the watch secret, as a header or as the browser's ?token=.
    let mut viewer = connect_with(&server.watch(), Some(WATCH))
        .await
        .expect("viewer admitted");
    assert!(matches!(
        next_text(&mut viewer).await,
        ServerMessage::Sessions { .. }
    ));
    let token_url = format!("{}?token={WATCH}", server.watch());
    connect_with(&token_url, None)
        .await
        .expect("viewer admitted by token");

    let base = format!("http://{}", server.addr);
    let (status, body) = http_request(&format!("{base}/v1/sessions"), "").await;
    assert_eq!(status, 401, "{body}");
    assert!(body.contains("\"unauthorized\""), "{body}");
    let header = format!("Authorization: Bearer {INGEST}\r\n");
    assert_eq!(
        http_request(&format!("{base}/v1/sessions"), &header)
            .await
            .0,
        401
    );
    let header = format!("Authorization: Bearer {WATCH}\r\n");
    assert_eq!(
        http_request(&format!("{base}/v1/sessions"), &header)
            .await
            .0,
        200
    );
    assert_eq!(
        http_request(&format!("{base}/v1/sessions?token={WATCH}"), "")
            .await
            .0,
        200
    );
    // Public: health and the page (no session data in either).
    assert_eq!(http_request(&format!("{base}/healthz"), "").await.0, 200);
    assert_eq!(http_request(&format!("{base}/"), "").await.0, 200);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_file_outside_the_page_is_served_whatever_the_path() {
    let server = TestServer::start(ServerOptions::default()).await;
    let base = format!("http://{}", server.addr);
    for path in [
        "/app/../Cargo.toml",
        "/app/%2e%2e/%2e%2e/Cargo.toml",
        "/app/..%2f..%2fCargo.toml",
        "/vendor/../../src/main.rs",
        "/vendor/three/%2e%2e/%2e%2e/%2e%2e/Cargo.toml",
        "/app//etc/passwd",
        "/app/%2fetc%2fpasswd",
        "/app/main.js%00.png",
        "/vendor/three/..\\..\\..\\Cargo.toml",
        "/etc/passwd",
        "/Cargo.toml",
    ] {
        let (status, body) = http_request(&format!("{base}{path}"), "").await;
        assert!(
            status == 404 || status == 400,
            "{path}: {status} {}",
            &body[..body.len().min(200)]
        );
        assert!(
            !body.contains("[package]") && !body.contains("root:"),
            "{path} leaked a file"
        );
    }
    assert_eq!(
        http_request(&format!("{base}/app/main.js"), "").await.0,
        200
    );
    server.stop().await;
}

/// Collects a headset's answers to `n` frames: (batches, errors by code, dropped).
async fn answers(ws: &mut Socket, n: usize) -> (usize, Vec<ErrorCode>, usize) {
    let (mut batches, mut errors, mut dropped) = (0, Vec::new(), 0);
    while batches + errors.len() + dropped < n {
        let m = tokio::time::timeout(Duration::from_secs(20), ws.next())
            .await
            .expect("answers within 20 s")
            .expect("open")
            .expect("readable");
        match m {
            Message::Binary(b) => {
                let batch = mrptv::protocol::decode_batch(&b).expect("batch");
                batches += usize::from(batch.kind == mrptv::protocol::BatchKind::Causal);
            }
            Message::Text(t) => match serde_json::from_str::<ServerMessage>(t.as_str()) {
                Ok(ServerMessage::Error { code, .. }) => errors.push(code),
                Ok(ServerMessage::Dropped { frame_indices, .. }) => dropped += frame_indices.len(),
                _ => {}
            },
            _ => {}
        }
    }
    (batches, errors, dropped)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn limits_refuse_with_clear_errors_and_free_up_again() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, _) = synth(&tmp.path().join("rec"), Scenario::Flume, 30);
    let server = TestServer::start(ServerOptions {
        max_sessions: 1,
        max_viewers_per_session: 1,
        max_image_side: 1000,
        max_frame_rate_hz: 10.0,
        ..Default::default()
    })
    .await;
    let mut a = connect(&server.ingest()).await;
    a.send(hello(&rec, |_| {})).await.expect("sends");
    assert!(matches!(
        next_text(&mut a).await,
        ServerMessage::Welcome { .. }
    ));
    let mut b = connect(&server.ingest()).await;
    let huge = hello(&rec, |v| {
        v["image"]["width"] = 5000.into();
        v["rig"]["image_size"] = serde_json::json!([5000, 480]);
    });
    let m = expect_error(&mut b, huge, ErrorCode::LimitReached).await;
    assert!(m.contains("--max-image-size"), "{m}");
    let m = expect_error(&mut b, hello(&rec, |_| {}), ErrorCode::LimitReached).await;
    assert!(m.contains("--max-sessions"), "{m}");

    let mut first = connect(&server.watch()).await;
    let mut second = connect(&server.watch()).await;
    next_text(&mut first).await;
    next_text(&mut second).await;
    let subscribe = |s: &str| Message::text(format!(r#"{{"type":"subscribe","session":"{s}"}}"#));
    first.send(subscribe("s1")).await.expect("sends");
    assert!(matches!(
        next_text(&mut first).await,
        ServerMessage::Subscribed { .. }
    ));
    let m = expect_error(&mut second, subscribe("s1"), ErrorCode::LimitReached).await;
    assert!(m.contains("--max-viewers"), "{m}");
    expect_error(&mut second, subscribe("*"), ErrorCode::LimitReached).await;

    // 30 frames at once against 10 frames/s: a second's worth passes, the rest is refused.
    for (i, entry) in rec.frames.iter().enumerate() {
        let (l, r) = rec.load(entry).expect("frame");
        a.send(frame(i as u64, entry.t_s, Encoding::Raw8, &l, &r))
            .await
            .expect("sends");
    }
    let (batches, errors, dropped) = answers(&mut a, 30).await;
    let limited = errors
        .iter()
        .filter(|c| **c == ErrorCode::RateLimited)
        .count();
    assert_eq!(limited, errors.len(), "only rate errors: {errors:?}");
    assert!(
        (19..=20).contains(&limited) && batches + dropped >= 10,
        "10 admitted (a 1 s burst, maybe one more refilled), the rest refused: {batches} batches, {dropped} dropped, {limited} limited"
    );

    // The session's slot frees when it ends.
    a.send(Message::text(r#"{"type":"bye"}"#))
        .await
        .expect("sends");
    loop {
        if let ServerMessage::Bye { counters, .. } = next_text(&mut a).await {
            let c = counters.expect("counters");
            assert_eq!(c.frames_rejected, limited as u64);
            break;
        }
    }
    b.send(hello(&rec, |_| {})).await.expect("sends");
    loop {
        match next_text(&mut b).await {
            ServerMessage::Welcome { .. } => break,
            // The session_ended/sessions traffic of the first is not for headsets; errors are.
            ServerMessage::Error { message, .. } => panic!("{message}"),
            _ => {}
        }
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hellos_at_the_same_moment_never_exceed_the_session_limit() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, _) = synth(&tmp.path().join("rec"), Scenario::Flume, 2);
    let record = tmp.path().join("recorded");
    let server = TestServer::start(ServerOptions {
        max_sessions: 2,
        // Recording makes starting a session slow (files created and synced): a wide window.
        record_dir: Some(record),
        ..Default::default()
    })
    .await;
    let mut sockets = Vec::new();
    for _ in 0..8 {
        sockets.push(connect(&server.ingest()).await);
    }
    let attempts = sockets.into_iter().map(|mut ws| {
        let hello = hello(&rec, |_| {});
        async move {
            ws.send(hello).await.expect("sends");
            let answer = next_text(&mut ws).await;
            (answer, ws)
        }
    });
    let answers = futures_util::future::join_all(attempts).await;
    let welcomed = answers
        .iter()
        .filter(|(a, _)| matches!(a, ServerMessage::Welcome { .. }))
        .count();
    let refused = answers
        .iter()
        .filter(|(a, _)| {
            matches!(a, ServerMessage::Error { code, .. } if *code == ErrorCode::LimitReached)
        })
        .count();
    assert_eq!((welcomed, refused), (2, 6));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_trickling_and_idle_peers_are_cut_off_quiet_ones_are_not() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, _) = synth(&tmp.path().join("rec"), Scenario::Flume, 4);
    let server = TestServer::start(ServerOptions {
        handshake_timeout: Duration::from_millis(600),
        idle_timeout: Duration::from_millis(1500),
        ..Default::default()
    })
    .await;
    let closed_within = |mut tcp: TcpStream, limit: Duration| async move {
        let started = std::time::Instant::now();
        let mut buf = [0u8; 256];
        loop {
            match tokio::time::timeout(limit, tcp.read(&mut buf)).await {
                Ok(Ok(0) | Err(_)) => return started.elapsed(),
                Ok(Ok(_)) => {}
                Err(_) => panic!("still open after {limit:?}"),
            }
        }
    };
    // Connects and says nothing.
    let silent = TcpStream::connect(server.addr).await.expect("connects");
    let waited = closed_within(silent, Duration::from_secs(5)).await;
    assert!(waited >= Duration::from_millis(500), "{waited:?}");
    // Sends half a request head, then trickles a byte every 100 ms: still cut off on time.
    let mut trickle = TcpStream::connect(server.addr).await.expect("connects");
    trickle
        .write_all(b"GET /healthz HTTP/1.1\r\n")
        .await
        .expect("writes");
    let dripping = tokio::spawn(async move {
        let started = std::time::Instant::now();
        while trickle.write_all(b"X").await.is_ok() {
            tokio::time::sleep(Duration::from_millis(100)).await;
            if started.elapsed() > Duration::from_secs(5) {
                panic!("trickling for 5 s: not cut off");
            }
        }
        started.elapsed()
    });
    let waited = dripping.await.expect("trickler");
    assert!(waited < Duration::from_secs(3), "{waited:?}");
    // A keep-alive request is answered and the connection closed: nobody parks a connection to
    // trickle a second request outside the deadline.
    let mut parked = TcpStream::connect(server.addr).await.expect("connects");
    parked
        .write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        .await
        .expect("writes");
    let mut answer = Vec::new();
    tokio::time::timeout(Duration::from_secs(2), parked.read_to_end(&mut answer))
        .await
        .expect("closed right after the answer")
        .expect("read");
    let answer = String::from_utf8_lossy(&answer).to_ascii_lowercase();
    assert!(
        answer.starts_with("http/1.1 200") && answer.contains("connection: close"),
        "{answer}"
    );

    // A headset that never says hello gets a bye saying why.
    let mut mute = connect(&server.ingest()).await;
    match next_text(&mut mute).await {
        ServerMessage::Bye { reason, .. } => assert!(reason.contains("no hello"), "{reason}"),
        other => panic!("{other:?}"),
    }

    // A quiet headset whose client library answers pings stays; one that stopped reading
    // (so never answers) is closed as idle.
    let mut quiet = connect(&server.ingest()).await;
    quiet.send(hello(&rec, |_| {})).await.expect("sends");
    // The deaf one never reads, so never answers a ping: a bare socket, read only at the end.
    let mut deaf = raw_ingest(server.addr).await;
    let hello_bytes = text_bytes(hello(&rec, |_| {}));
    deaf.write_all(&ws_frame(1, hello_bytes.len(), &hello_bytes))
        .await
        .expect("hello");
    // A viewer only receives; its library answers the pings, so it stays too.
    let mut viewer = connect(&server.watch()).await;
    viewer
        .send(Message::text(r#"{"type":"subscribe","session":"*"}"#))
        .await
        .expect("subscribes");
    let watching = tokio::spawn(async move {
        let until = tokio::time::Instant::now() + Duration::from_millis(3500);
        let mut pings = 0;
        while let Ok(m) = tokio::time::timeout_at(until, viewer.next()).await {
            match m.expect("open").expect("readable") {
                Message::Ping(_) => pings += 1,
                Message::Text(t) => assert!(!t.as_str().contains("\"bye\""), "{}", t.as_str()),
                Message::Close(c) => panic!("viewer closed: {c:?}"),
                _ => {}
            }
        }
        pings
    });
    let until = tokio::time::Instant::now() + Duration::from_millis(3500);
    let mut pings = 0;
    while let Ok(m) = tokio::time::timeout_at(until, quiet.next()).await {
        match m.expect("open").expect("readable") {
            Message::Ping(_) => pings += 1,
            Message::Text(t) => assert!(!t.as_str().contains("\"bye\""), "{}", t.as_str()),
            _ => {}
        }
    }
    assert!(pings >= 3, "pinged every 0.5 s: {pings}");
    let viewer_pings = watching.await.expect("the viewer stayed");
    assert!(viewer_pings >= 3, "viewer pinged too: {viewer_pings}");
    let mut received = Vec::new();
    tokio::time::timeout(Duration::from_secs(5), deaf.read_to_end(&mut received))
        .await
        .expect("the server closed the deaf headset's connection")
        .expect("read");
    let received = String::from_utf8_lossy(&received);
    assert!(
        received.contains(r#""type":"bye","reason":"idle: nothing received for 1.5 s""#),
        "{received}"
    );
    quiet
        .send(Message::text(r#"{"type":"bye"}"#))
        .await
        .expect("the quiet headset is still connected");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_beyond_the_limit_are_closed_and_the_server_recovers() {
    let server = TestServer::start(ServerOptions {
        max_connections: 2,
        ..Default::default()
    })
    .await;
    let held: Vec<TcpStream> = vec![
        TcpStream::connect(server.addr).await.expect("connects"),
        TcpStream::connect(server.addr).await.expect("connects"),
    ];
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut third = TcpStream::connect(server.addr).await.expect("connects");
    let _ = third
        .write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        .await;
    let mut answer = Vec::new();
    let read = tokio::time::timeout(Duration::from_secs(5), third.read_to_end(&mut answer))
        .await
        .expect("closed at once, not left hanging");
    assert!(
        read.is_err() || answer.is_empty(),
        "no answer beyond the limit: {}",
        String::from_utf8_lossy(&answer)
    );
    drop(held);
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert!(http_get(&format!("http://{}/healthz", server.addr))
        .await
        .contains("\"ok\""));
    server.stop().await;
}

fn binary(bytes: Vec<u8>) -> Message {
    Message::binary(bytes)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_kind_of_bad_input_gets_a_clear_error_and_others_stream_on() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Flume, 40);
    let server = TestServer::start(ServerOptions {
        max_message_bytes: 1 << 20,
        ..Default::default()
    })
    .await;
    let good = spawn_replay(&rec, replay_options(server.ingest(), &config));
    let (left, right) = rec.load(&rec.frames[0]).expect("frame 0");
    let (w, h) = (rec.rig.width as usize, rec.rig.height as usize);

    // Calibration: non-finite, singular, not a rotation; each names its field.
    let mut ws = connect(&server.ingest()).await;
    let hello_text = match hello(&rec, |_| {}) {
        Message::Text(t) => t.as_str().to_string(),
        _ => unreachable!(),
    };
    let rig = serde_json::to_value(rec.rig.to_file()).expect("rig json");
    for (key, value, field) in [
        // JSON has no NaN; an overflowing literal is the nearest a client can send.
        ("K1", "[[1e999,0,320],[0,500,240],[0,0,1]]", None),
        ("R", "[[1,0,0],[0,1,0],[0,0,0]]", Some("R")),
        ("R", "[[1,0,0],[0,2,0],[0,0,1]]", Some("R")),
        ("T", "[0.1,\"x\",0]", None),
        ("T", "[0,0,0]", Some("T")),
        ("K2", "[[500,0,320],[0,500,240],[0,0,0]]", Some("K2")),
        ("K2", "[[-500,0,320],[0,500,240],[0,0,1]]", Some("K2")),
        ("D1", "[0.1,0.2]", Some("D1")),
    ] {
        let old = format!("\"{key}\":{}", rig[key]);
        let edited = hello_text.replacen(&old, &format!("\"{key}\":{value}"), 1);
        assert_ne!(edited, hello_text, "{key} edited");
        ws.send(Message::text(edited)).await.expect("sends");
        match next_text(&mut ws).await {
            ServerMessage::Error { code, message, .. } => {
                assert!(
                    matches!(
                        code,
                        ErrorCode::BadCalibration | ErrorCode::BadHello | ErrorCode::MalformedJson
                    ),
                    "{key}={value}: {code:?} {message}"
                );
                if let Some(field) = field {
                    assert!(
                        message.contains(field),
                        "{key}={value}: names {field}: {message}"
                    );
                }
            }
            other => panic!("{key}={value}: {other:?}"),
        }
    }

    // A PNG session: bytes that are not a PNG, and a PNG of the wrong size.
    ws.send(hello(&rec, |v| v["image"]["encoding"] = "png".into()))
        .await
        .expect("sends");
    assert!(matches!(
        next_text(&mut ws).await,
        ServerMessage::Welcome { .. }
    ));
    let not_png = frame(
        0,
        0.0,
        Encoding::Png,
        b"GIF89a not a png",
        b"\x89PNG\r\n\x1a\n",
    );
    let m = expect_error(&mut ws, not_png, ErrorCode::BadImage).await;
    assert!(m.contains("left image"), "{m}");
    let small = mrptv::recording::encode_gray_png(&[0u8; 64], 8, 8).expect("png");
    let m = expect_error(
        &mut ws,
        frame(1, 0.1, Encoding::Png, &small, &small),
        ErrorCode::BadImage,
    )
    .await;
    assert!(m.contains("8x8") || m.contains("size"), "{m}");
    ws.send(Message::text(r#"{"type":"bye"}"#))
        .await
        .expect("sends");

    // A raw8 session: poses, timestamps, lengths, degenerate images.
    let mut ws = connect(&server.ingest()).await;
    ws.send(hello(&rec, |_| {})).await.expect("sends");
    assert!(matches!(
        next_text(&mut ws).await,
        ServerMessage::Welcome { .. }
    ));
    let posed = |index: u64, t_s: f64, edit: &dyn Fn(&mut Vec<u8>)| {
        let mut b = encode_frame(&FrameMessage {
            encoding: Encoding::Raw8,
            frame_index: index,
            t_s,
            world_from_rig: Some(nalgebra::Isometry3::identity()),
            left: &left,
            right: &right,
        })
        .expect("encodes");
        edit(&mut b);
        binary(b)
    };
    // The pose's 16 f64 follow the 32-byte header, row-major: m03 (x translation) at 32 + 3 * 8.
    for (what, offset, value) in [
        ("NaN rotation", 32, f64::NAN),
        ("infinite rotation", 32 + 5 * 8, f64::INFINITY),
        ("NaN translation", 32 + 3 * 8, f64::NAN),
        ("infinite translation", 32 + 7 * 8, f64::NEG_INFINITY),
        ("bottom row", 32 + 15 * 8, 2.0),
    ] {
        let m = expect_error(
            &mut ws,
            posed(0, 0.0, &|b| {
                b[offset..offset + 8].copy_from_slice(&value.to_le_bytes())
            }),
            ErrorCode::BadFrame,
        )
        .await;
        assert!(m.contains("world_from_rig"), "{what}: {m}");
    }
    expect_error(
        &mut ws,
        frame(0, f64::INFINITY, Encoding::Raw8, &left, &right),
        ErrorCode::BadTimestamp,
    )
    .await;
    expect_error(
        &mut ws,
        frame(0, f64::NEG_INFINITY, Encoding::Raw8, &left, &right),
        ErrorCode::BadTimestamp,
    )
    .await;
    // Lengths: an empty message, a header alone, one image short, one byte long.
    expect_error(&mut ws, binary(Vec::new()), ErrorCode::BadFrame).await;
    let whole = match frame(0, 0.0, Encoding::Raw8, &left, &right) {
        Message::Binary(b) => b.to_vec(),
        _ => unreachable!(),
    };
    expect_error(&mut ws, binary(whole[..32].to_vec()), ErrorCode::BadFrame).await;
    let mut long = whole.clone();
    long.push(0);
    expect_error(&mut ws, binary(long), ErrorCode::BadFrame).await;
    let short = frame(0, 0.0, Encoding::Raw8, &left[..w * h - 1], &right);
    expect_error(&mut ws, short, ErrorCode::BadImage).await;

    // All black, all white: no particles, no vectors, no error.
    let black = vec![0u8; w * h];
    let white = vec![255u8; w * h];
    ws.send(frame(1, 1.0, Encoding::Raw8, &black, &black))
        .await
        .expect("sends");
    assert_eq!(next_binary(&mut ws).await.vectors.len(), 0);
    ws.send(frame(2, 2.0, Encoding::Raw8, &white, &white))
        .await
        .expect("sends");
    assert_eq!(next_binary(&mut ws).await.vectors.len(), 0);
    // Time: the same timestamp again, then one going back.
    let m = expect_error(
        &mut ws,
        frame(3, 2.0, Encoding::Raw8, &left, &right),
        ErrorCode::BadTimestamp,
    )
    .await;
    assert!(m.contains("frame 3"), "{m}");
    expect_error(
        &mut ws,
        frame(4, 1.5, Encoding::Raw8, &left, &right),
        ErrorCode::BadTimestamp,
    )
    .await;
    // Index: repeated.
    expect_error(
        &mut ws,
        frame(2, 3.0, Encoding::Raw8, &left, &right),
        ErrorCode::BadFrame,
    )
    .await;
    ws.send(frame(5, 3.0, Encoding::Raw8, &left, &right))
        .await
        .expect("sends");
    assert_eq!(next_binary(&mut ws).await.frame_index, 5);

    // Oversize (over --max-message-mib): told why, then the connection closes. The server stops
    // reading at the oversize header, so the rest of the message is unread when it closes, and
    // TCP answers it with a reset: a client still sending then, or slow to read, can lose the
    // error text to the reset (protocol/README.md, Limits). Anything else is a failure.
    let is_reset = |e: &tokio_tungstenite::tungstenite::Error| {
        matches!(e, tokio_tungstenite::tungstenite::Error::Io(io)
            if io.kind() == std::io::ErrorKind::ConnectionReset)
    };
    let mut reset = match ws.send(binary(vec![7u8; (1 << 20) + 1])).await {
        Ok(()) => false,
        Err(e) => {
            assert!(is_reset(&e), "sends: {e}");
            true
        }
    };
    let mut told = None;
    let mut closed = reset;
    while let Ok(Some(m)) = tokio::time::timeout(Duration::from_secs(10), ws.next()).await {
        match m {
            Ok(Message::Text(t)) => {
                if let Ok(ServerMessage::Error { message, .. }) = serde_json::from_str(t.as_str()) {
                    told = Some(message);
                }
            }
            Ok(Message::Close(_)) => {
                closed = true;
                break;
            }
            Err(e) => {
                reset |= is_reset(&e);
                closed = true;
                break;
            }
            _ => {}
        }
    }
    match told {
        Some(told) => assert!(told.contains("too long") || told.contains("size"), "{told}"),
        None => assert!(
            reset,
            "no error before the close, and no reset to lose it to"
        ),
    }
    assert!(
        closed || ws.next().await.is_none(),
        "closed after an oversize message"
    );

    let report = good.await.expect("good headset");
    assert!(report.errors.is_empty(), "{:?}", report.errors);
    assert_eq!(report.counters.map(|c| c.frames_processed), Some(40));
    assert!(http_get(&format!("http://{}/healthz", server.addr))
        .await
        .contains("\"ok\""));
    server.stop().await;
}

/// A WebSocket client frame, masked as clients must.
fn ws_frame(opcode: u8, payload_len: usize, payload: &[u8]) -> Vec<u8> {
    let mask = [0x12u8, 0x34, 0x56, 0x78];
    let mut f = vec![0x80 | opcode];
    if payload_len < 126 {
        f.push(0x80 | payload_len as u8);
    } else if payload_len < 65536 {
        f.push(0x80 | 126);
        f.extend_from_slice(&(payload_len as u16).to_be_bytes());
    } else {
        f.push(0x80 | 127);
        f.extend_from_slice(&(payload_len as u64).to_be_bytes());
    }
    f.extend_from_slice(&mask);
    f.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
    f
}

/// A WebSocket to `/v1/ingest` by hand, on a bare TCP stream the test fully controls.
async fn raw_ingest(addr: std::net::SocketAddr) -> TcpStream {
    let mut tcp = TcpStream::connect(addr).await.expect("connects");
    let request = format!(
        "GET /v1/ingest HTTP/1.1\r\nHost: {addr}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    );
    tcp.write_all(request.as_bytes()).await.expect("writes");
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        tcp.read_exact(&mut byte).await.expect("upgrade answer");
        head.push(byte[0]);
    }
    assert!(head.starts_with(b"HTTP/1.1 101"));
    tcp
}

fn text_bytes(m: Message) -> Vec<u8> {
    match m {
        Message::Text(t) => t.as_str().as_bytes().to_vec(),
        _ => unreachable!("a text message"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_headset_vanishing_mid_frame_ends_only_its_own_session() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Flume, 60);
    let server = TestServer::start(ServerOptions::default()).await;
    let good = spawn_replay(
        &rec,
        ReplayOptions {
            rate: mrptv::client::Rate::Recorded,
            ..replay_options(server.ingest(), &config)
        },
    );
    for cut in [0usize, 1, 2, 14, 5000] {
        let mut tcp = raw_ingest(server.addr).await;
        let hello_bytes = text_bytes(hello(&rec, |_| {}));
        tcp.write_all(&ws_frame(1, hello_bytes.len(), &hello_bytes))
            .await
            .expect("hello");
        // Wait for the welcome to be sure the session is live, then send part of a frame.
        let mut buf = [0u8; 4096];
        let n = tcp.read(&mut buf).await.expect("welcome");
        assert!(String::from_utf8_lossy(&buf[..n]).contains("welcome"));
        let (l, r) = rec.load(&rec.frames[0]).expect("frame");
        let whole = match frame(0, 0.0, Encoding::Raw8, &l, &r) {
            Message::Binary(b) => b.to_vec(),
            _ => unreachable!(),
        };
        let framed = ws_frame(2, whole.len(), &whole);
        tcp.write_all(&framed[..cut.min(framed.len())])
            .await
            .expect("part of a frame");
        drop(tcp);
    }
    // Their sessions end; the server and the good session carry on.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        let body = http_get(&format!("http://{}/v1/sessions", server.addr)).await;
        let live: serde_json::Value = serde_json::from_str(&body).expect("json");
        let clients: Vec<String> = live["sessions"]
            .as_array()
            .expect("list")
            .iter()
            .map(|s| s["client"].as_str().unwrap_or("").to_string())
            .collect();
        if !clients.iter().any(|c| c == "bad-message test") {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "cut sessions still live: {clients:?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let report = good.await.expect("good headset");
    assert!(report.errors.is_empty(), "{:?}", report.errors);
    assert_eq!(report.counters.map(|c| c.frames_processed), Some(60));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rerun_viewer_going_away_mid_session_loses_nothing_else() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, config) = synth(&tmp.path().join("rec"), Scenario::Flume, 45);
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let mut sinks = vec![RerunSink::Serve(port)];
    let proxy = tokio::task::spawn_blocking(move || {
        let proxy = start_proxy(&mut sinks).expect("proxy starts");
        (proxy, sinks)
    })
    .await
    .expect("proxy task");
    let (proxy, sinks) = proxy;
    let server = TestServer::start(ServerOptions {
        rerun: Some(RerunOptions {
            sinks,
            ..Default::default()
        }),
        ..Default::default()
    })
    .await;
    // Streams at the recording's 30 Hz: 1.5 s, of which the viewer sees the first half.
    let streaming = spawn_replay(
        &rec,
        ReplayOptions {
            rate: mrptv::client::Rate::Recorded,
            ..replay_options(server.ingest(), &config)
        },
    );
    tokio::time::sleep(Duration::from_millis(700)).await;
    tokio::task::spawn_blocking(move || drop(proxy))
        .await
        .expect("the viewer's server stops");
    let report = streaming.await.expect("replay");
    assert!(report.errors.is_empty(), "{:?}", report.errors);
    assert_eq!(report.counters.map(|c| c.frames_processed), Some(45));
    assert_eq!(report.causal_batches, 45);
    // A session started after the sink vanished runs too.
    let again = replay(&rec, &replay_options(server.ingest(), &config)).await;
    assert_eq!(again.counters.map(|c| c.frames_processed), Some(45));
    server.stop().await;
}

/// Reads until the server closes: every text message before the close, and the close code.
async fn until_closed(ws: &mut Socket) -> (Vec<ServerMessage>, Option<u16>) {
    let mut texts = Vec::new();
    loop {
        let m = tokio::time::timeout(Duration::from_secs(20), ws.next())
            .await
            .expect("the server closes within 20 s");
        match m {
            Some(Ok(Message::Text(t))) => {
                texts.push(serde_json::from_str(t.as_str()).expect("server JSON"))
            }
            Some(Ok(Message::Close(frame))) => {
                return (texts, frame.map(|f| u16::from(f.code)));
            }
            Some(Ok(_)) => {}
            Some(Err(e)) => panic!("not a clean close: {e} (after {texts:?})"),
            None => panic!("the connection ended without a close frame (after {texts:?})"),
        }
    }
}

/// A 640x480 (or any size) grayscale PNG at 1, 2 or 4 bits a pixel, all black.
fn packed_gray_png(width: u32, height: u32, depth: png::BitDepth) -> Vec<u8> {
    let mut bytes = Vec::new();
    let mut encoder = png::Encoder::new(&mut bytes, width, height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(depth);
    let row_bytes = (width as usize * depth as usize).div_ceil(8);
    let mut writer = encoder.write_header().expect("header");
    writer
        .write_image_data(&vec![0u8; row_bytes * height as usize])
        .expect("data");
    writer.finish().expect("finish");
    bytes
}

/// What an independent client written from `protocol/` alone found the server doing otherwise:
/// each rule as the spec now states it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_does_what_the_protocol_says() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, _) = synth(&tmp.path().join("rec"), Scenario::Flume, 3);
    let (w, h) = (rec.rig.width, rec.rig.height);
    let server = TestServer::start(ServerOptions::default()).await;
    let mut ws = connect(&server.ingest()).await;

    // Anything wrong inside `rig` is the calibration's, an unknown key included.
    let m = expect_error(
        &mut ws,
        hello(&rec, |v| v["rig"]["typo"] = serde_json::json!(1)),
        ErrorCode::BadCalibration,
    )
    .await;
    assert!(m.contains("typo"), "{m}");
    ws.send(hello(&rec, |v| v["image"]["encoding"] = "png".into()))
        .await
        .expect("sends");
    assert!(matches!(
        next_text(&mut ws).await,
        ServerMessage::Welcome { .. }
    ));

    // PNGs of fewer than 8 bits a pixel are refused, as `process` refuses them; a refused
    // frame's index may be sent again.
    for depth in [png::BitDepth::One, png::BitDepth::Two, png::BitDepth::Four] {
        let packed = packed_gray_png(w, h, depth);
        let m = expect_error(
            &mut ws,
            frame(0, 0.0, Encoding::Png, &packed, &packed),
            ErrorCode::BadImage,
        )
        .await;
        assert!(m.contains("8-bit grayscale"), "{depth:?}: {m}");
    }
    let left = std::fs::read(rec.left_path(0)).expect("left PNG");
    let right = std::fs::read(rec.right_path(0)).expect("right PNG");
    ws.send(frame(0, 0.0, Encoding::Png, &left, &right))
        .await
        .expect("sends");
    assert_eq!(next_binary(&mut ws).await.frame_index, 0);
    // Refused by the pipeline (a timestamp not after the last one), then sent again corrected.
    expect_error(
        &mut ws,
        frame(1, 0.0, Encoding::Png, &left, &right),
        ErrorCode::BadTimestamp,
    )
    .await;
    ws.send(frame(1, 0.1, Encoding::Png, &left, &right))
        .await
        .expect("sends");
    assert_eq!(next_binary(&mut ws).await.frame_index, 1);
    // An accepted index is spent.
    expect_error(
        &mut ws,
        frame(1, 0.2, Encoding::Png, &left, &right),
        ErrorCode::BadFrame,
    )
    .await;

    // Viewers: messages with fields they do not have are refused; `viewers` counts the
    // subscribers to "*" as well as those to the session by name.
    let mut all = connect(&server.watch()).await;
    let mut one = connect(&server.watch()).await;
    for (viewer, target) in [(&mut all, "*"), (&mut one, "s1")] {
        assert!(matches!(
            next_text(viewer).await,
            ServerMessage::Sessions { .. }
        ));
        for extra in [
            r#"{"type":"list","all":true}"#,
            r#"{"type":"unsubscribe","session":"s1"}"#,
        ] {
            expect_error(viewer, Message::text(extra), ErrorCode::MalformedJson).await;
        }
        let subscribe = format!(r#"{{"type":"subscribe","session":"{target}"}}"#);
        viewer.send(Message::text(subscribe)).await.expect("sends");
        assert!(matches!(
            next_text(viewer).await,
            ServerMessage::Subscribed { .. }
        ));
    }
    let listed = http_get(&format!("http://{}/v1/sessions", server.addr)).await;
    assert!(listed.contains(r#""viewers":2"#), "{listed}");
    // A viewer's close is answered with a close.
    one.send(Message::Close(None)).await.expect("sends");
    let (_, code) = until_closed(&mut one).await;
    assert_eq!(code, None, "the answer echoes the viewer's (empty) close");

    // A bye with a field bye does not have is refused, and the session goes on.
    expect_error(
        &mut ws,
        Message::text(r#"{"type":"bye","reason":"done"}"#),
        ErrorCode::MalformedJson,
    )
    .await;
    ws.send(frame(2, 0.2, Encoding::Png, &left, &right))
        .await
        .expect("sends");
    assert_eq!(next_binary(&mut ws).await.frame_index, 2);
    // A headset's close is answered with a close, and ends its session like a disconnect.
    ws.send(Message::Close(Some(
        tokio_tungstenite::tungstenite::protocol::CloseFrame {
            code: 1000.into(),
            reason: "done".into(),
        },
    )))
    .await
    .expect("sends");
    let (_, code) = until_closed(&mut ws).await;
    assert_eq!(code, Some(1000));
    loop {
        if let ServerMessage::SessionEnded { session, .. } = next_text(&mut all).await {
            assert_eq!(session, "s1");
            break;
        }
    }
    server.stop().await;
    let (texts, code) = until_closed(&mut all).await;
    assert!(
        matches!(texts.last(), Some(ServerMessage::Bye { .. })),
        "{texts:?}"
    );
    assert_eq!(code, Some(1000), "every close from the server is 1000");
}

/// At shutdown a viewer of every session gets each live session's `session_ended`, then the
/// emptied `sessions` list, then `bye` and a 1000 close: always, not by luck of timing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn at_shutdown_viewers_always_hear_the_sessions_end_before_their_bye() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (rec, _) = synth(&tmp.path().join("rec"), Scenario::Flume, 1);
    let blank = vec![0u8; (rec.rig.width * rec.rig.height) as usize];
    for round in 0..200 {
        let server = TestServer::start(ServerOptions::default()).await;
        let mut headset = connect(&server.ingest()).await;
        headset.send(hello(&rec, |_| {})).await.expect("sends");
        assert!(matches!(
            next_text(&mut headset).await,
            ServerMessage::Welcome { .. }
        ));
        let mut viewer = connect(&server.watch()).await;
        viewer
            .send(Message::text(r#"{"type":"subscribe","session":"*"}"#))
            .await
            .expect("sends");
        loop {
            if let ServerMessage::Subscribed { .. } = next_text(&mut viewer).await {
                break;
            }
        }
        // A frame in flight as the stop comes, every other round.
        if round % 2 == 1 {
            headset
                .send(frame(0, 0.0, Encoding::Raw8, &blank, &blank))
                .await
                .expect("sends");
        }
        server.stop().await;
        let (texts, code) = until_closed(&mut viewer).await;
        let ended = texts.iter().position(
            |m| matches!(m, ServerMessage::SessionEnded { session, .. } if session == "s1"),
        );
        let emptied = texts.iter().rposition(
            |m| matches!(m, ServerMessage::Sessions { sessions } if sessions.is_empty()),
        );
        let bye = texts.iter().position(
            |m| matches!(m, ServerMessage::Bye { reason, .. } if reason == "server shutting down"),
        );
        assert!(
            matches!((ended, emptied, bye), (Some(e), Some(s), Some(b)) if e < s && s < b && b + 1 == texts.len()),
            "round {round}: {texts:?}"
        );
        assert_eq!(code, Some(1000), "round {round}");
        let (texts, code) = until_closed(&mut headset).await;
        assert!(
            matches!(texts.last(), Some(ServerMessage::Bye { reason, .. }) if reason == "server shutting down"),
            "round {round}: {texts:?}"
        );
        assert_eq!(code, Some(1000), "round {round}");
    }
}
