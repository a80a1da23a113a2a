//! The viewer of a training run facing hostile clients: crowds of connections, clients that dribble a byte
//! a second, oversized and malformed messages, paths outside the page and wrong tokens at a high rate. Each
//! gets its HTTP or WebSocket error or is closed within the idle time; meanwhile the run trains, a
//! well-behaved page keeps getting frames, and afterwards the server holds no more descriptors or threads
//! than before. The figures it prints are those the docs quote (`--nocapture`).

use std::io::{ErrorKind, Read, Write};
use std::net::TcpStream;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde_json::json;
use tungstenite::protocol::frame::coding::CloseCode;
use tungstenite::Message;

use super::{get, receive, scratch, send, serve, Reply, Socket};

/// The idle time the test's server is given (`--idle-timeout`).
const IDLE: Duration = Duration::from_secs(3);

/// How long past the idle time a close may come (a ping is sent a third of it apart; the machine is busy).
const SLACK: Duration = Duration::from_secs(4);

/// The server's resident memory (kB), open descriptors and threads.
fn usage(pid: u32) -> (u64, usize, usize) {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let field = |name: &str| -> u64 {
        let line = status.lines().find(|l| l.starts_with(name)).unwrap();
        line.split_whitespace().nth(1).unwrap().parse().unwrap()
    };
    let fds = std::fs::read_dir(format!("/proc/{pid}/fd")).unwrap().count();
    (field("VmRSS:"), fds, field("Threads:") as usize)
}

/// A page of the viewer at `address`, or the HTTP status that refused it.
fn open_page(address: &str, token: &str) -> Result<Socket, u16> {
    let stream = TcpStream::connect(address).unwrap();
    stream.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    let url = format!("ws://{address}/ws?token={token}");
    match tungstenite::client(url.as_str(), stream) {
        Ok((socket, _)) => Ok(socket),
        Err(tungstenite::HandshakeError::Failure(tungstenite::Error::Http(response))) => {
            Err(response.status().as_u16())
        }
        Err(e) => panic!("the handshake fails: {e}"),
    }
}

/// A page, waiting (up to 10 s) for one that closed a moment ago to give up its place.
fn page(address: &str, token: &str) -> Socket {
    let start = Instant::now();
    loop {
        match open_page(address, token) {
            Ok(socket) => return socket,
            Err(503) if start.elapsed() < Duration::from_secs(10) => {
                std::thread::sleep(Duration::from_millis(100))
            }
            Err(status) => panic!("a page is refused with {status}"),
        }
    }
}

/// What the well-behaved page saw: the time from each camera request to its first frame.
struct Witness {
    latencies: Vec<Duration>,
}

/// A well-behaved page: asks for a frame, waits for it, rests 200 ms and asks again until `stop`; always
/// reading, so it answers the server's pings. `step` follows the run's progress records.
fn good_page(mut socket: Socket, stop: Arc<AtomicBool>, step: Arc<AtomicU64>) -> JoinHandle<Witness> {
    std::thread::spawn(move || {
        let camera = json!({"eye": [-2.5, 0.3, 0.0], "target": [0, 0, 0], "up": [0, 1, 0], "focal": 1.0});
        let mut latencies = Vec::new();
        let mut id = 0;
        while !stop.load(Ordering::Relaxed) {
            id += 1;
            let asked = Instant::now();
            send(&mut socket, super::camera_request(id, &camera, 32, 32, "color"));
            loop {
                match receive(&mut socket) {
                    Reply::Frame(header, _) if header["camera_id"] == id => break,
                    Reply::Json(m) if m["type"] == "progress" => {
                        step.fetch_max(m["record"]["step"].as_u64().unwrap(), Ordering::Relaxed);
                    }
                    Reply::Json(m) if m["type"] == "error" => panic!("the good page got {m}"),
                    _ => {}
                }
            }
            latencies.push(asked.elapsed());
            let rest = Instant::now();
            while rest.elapsed() < Duration::from_millis(200) {
                socket
                    .get_mut()
                    .set_read_timeout(Some(Duration::from_millis(50)))
                    .unwrap();
                match socket.read() {
                    Ok(_) => {}
                    Err(tungstenite::Error::Io(e))
                        if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
                    Err(e) => panic!("the good page was dropped: {e}"),
                }
            }
            socket
                .get_mut()
                .set_read_timeout(Some(Duration::from_secs(60)))
                .unwrap();
        }
        Witness { latencies }
    })
}

fn median(values: &[Duration]) -> Duration {
    let mut sorted = values.to_vec();
    sorted.sort();
    sorted[sorted.len() / 2]
}

/// Reads `stream` to its end (or until `limit`); the bytes and how long until the server closed it.
fn read_to_close(stream: &mut TcpStream, limit: Duration) -> (Vec<u8>, Duration) {
    let start = Instant::now();
    stream.set_read_timeout(Some(Duration::from_millis(200))).unwrap();
    let mut bytes = Vec::new();
    let mut chunk = [0u8; 4096];
    while start.elapsed() < limit {
        match stream.read(&mut chunk) {
            Ok(0) => return (bytes, start.elapsed()),
            Ok(n) => bytes.extend_from_slice(&chunk[..n]),
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
            Err(_) => return (bytes, start.elapsed()),
        }
    }
    panic!("the server kept the connection open for {limit:?}");
}

/// `count` connections that send nothing: how many the server held (then closed within the idle time) and
/// how many it refused with 503 at once.
fn crowd(address: &str, count: usize) -> (usize, usize) {
    let mut streams: Vec<TcpStream> = (0..count).map(|_| TcpStream::connect(address).unwrap()).collect();
    let (mut held, mut refused) = (0, 0);
    for stream in &mut streams {
        let (bytes, waited) = read_to_close(stream, IDLE + SLACK + SLACK);
        if bytes.starts_with(b"HTTP/1.1 503") {
            refused += 1;
        } else {
            assert!(bytes.is_empty(), "{}", String::from_utf8_lossy(&bytes));
            held += 1;
        }
        assert!(waited < IDLE + SLACK, "a silent connection lived {waited:?}");
    }
    (held, refused)
}

/// A client that sends `bytes` one a second (never all of them), reading what comes in between: how long
/// until the server closed it.
fn dribble(stream: &mut TcpStream, bytes: &[u8]) -> Duration {
    let start = Instant::now();
    let mut sink = [0u8; 4096];
    for byte in bytes {
        if stream.write_all(&[*byte]).is_err() {
            return start.elapsed();
        }
        let second = Instant::now();
        while second.elapsed() < Duration::from_secs(1) {
            stream.set_read_timeout(Some(Duration::from_millis(100))).unwrap();
            match stream.read(&mut sink) {
                Ok(0) => return start.elapsed(),
                Ok(_) => {}
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
                Err(_) => return start.elapsed(),
            }
        }
    }
    panic!("the server read all {} dribbled bytes", bytes.len());
}

/// A client frame: `head` (FIN and opcode), masked with a fixed key, or not.
fn frame(head: u8, payload: &[u8], masked: bool) -> Vec<u8> {
    let key = [0x37, 0xfa, 0x21, 0x3d];
    let mut bytes = vec![head];
    let mask_bit = if masked { 0x80 } else { 0 };
    match payload.len() {
        n if n < 126 => bytes.push(mask_bit | n as u8),
        n => {
            bytes.push(mask_bit | 126);
            bytes.extend_from_slice(&(n as u16).to_be_bytes());
        }
    }
    if masked {
        bytes.extend_from_slice(&key);
        bytes.extend(payload.iter().enumerate().map(|(i, b)| b ^ key[i % 4]));
    } else {
        bytes.extend_from_slice(payload);
    }
    bytes
}

/// Writes `bytes` raw on a page's socket and reads until the server's close frame: its code.
fn close_code_for(address: &str, token: &str, bytes: &[u8]) -> CloseCode {
    let mut socket = page(address, token);
    socket.get_mut().write_all(bytes).unwrap();
    loop {
        match socket.read() {
            Ok(Message::Close(Some(close))) => return close.code,
            Ok(Message::Close(None)) => panic!("a close without a code"),
            Ok(_) => {}
            Err(e) => panic!("no close frame came: {e}"),
        }
    }
}

#[test]
fn a_training_run_keeps_training_and_serving_while_hostile_clients_are_turned_away() {
    let dir = scratch("hostile");
    crate::common::make_views(&dir);
    std::fs::write(dir.join("train.sdf"), crate::common::trainer_with(1_000_000, "")).unwrap();
    let idle = IDLE.as_secs().to_string();
    let viewer = serve(
        &[
            "run",
            "train.sdf",
            "--view",
            "--port",
            "0",
            "--idle-timeout",
            &idle,
            "--max-pages",
            "10",
        ],
        &dir,
    );
    let (address, token, pid) = (viewer.address.clone(), viewer.token.clone(), viewer.child.id());

    let stop = Arc::new(AtomicBool::new(false));
    let step = Arc::new(AtomicU64::new(0));
    let witness = good_page(page(&address, &token), Arc::clone(&stop), Arc::clone(&step));
    std::thread::sleep(Duration::from_secs(4));
    let (rss_before, fds_before, threads_before) = usage(pid);
    let step_before = step.load(Ordering::Relaxed);
    assert!(step_before > 0, "the run trains");
    let attack = Instant::now();

    // A crowd: 300 silent connections, the default limit of 256 open at once (pages count apart).
    let (held, refused) = crowd(&address, 300);
    eprintln!(
        "crowd: {held} connections held and closed when silent for the idle time, {refused} refused (503)"
    );
    assert_eq!((held, refused), (256, 44));

    // Slow clients: a request's head and a WebSocket frame dribbled a byte a second, eight of each.
    let head = format!("GET /?token={token} HTTP/1.1\r\nHost: x\r\n\r\n");
    let text = frame(0x81, br#"{"type": "camera", "id": 1}"#, true);
    let slow: Vec<JoinHandle<Duration>> = (0..16)
        .map(|i| {
            let (address, token, head, text) = (address.clone(), token.clone(), head.clone(), text.clone());
            std::thread::spawn(move || {
                if i % 2 == 0 {
                    dribble(&mut TcpStream::connect(&address).unwrap(), head.as_bytes())
                } else {
                    let mut socket = page(&address, &token);
                    dribble(socket.get_mut(), &text)
                }
            })
        })
        .collect();
    let waits: Vec<Duration> = slow.into_iter().map(|h| h.join().unwrap()).collect();
    eprintln!(
        "slow clients: 16 survived, each closed after {:.1}-{:.1} s",
        waits.iter().min().unwrap().as_secs_f64(),
        waits.iter().max().unwrap().as_secs_f64()
    );
    for wait in &waits {
        assert!(*wait < IDLE + IDLE / 3 + SLACK, "a slow client lived {wait:?}");
    }

    // The pages' limit (10): the good page and nine more are open, the next is refused.
    let nine: Vec<Socket> = (0..9).map(|_| page(&address, &token)).collect();
    assert_eq!(open_page(&address, &token).err(), Some(503));
    drop(nine);

    // Oversized: a frame that declares 1 GB is closed with 1009 before its payload is read; 100 MB sent
    // are not taken; a request declaring a 1 GB body is answered.
    let mut huge = vec![0x81, 0xff];
    huge.extend_from_slice(&(1u64 << 30).to_be_bytes());
    huge.extend_from_slice(&[1, 2, 3, 4]);
    assert_eq!(close_code_for(&address, &token, &huge), CloseCode::Size);
    let mut socket = page(&address, &token);
    let mut flood = frame(0x82, &[], true);
    flood[1] = 0xff;
    flood.splice(2..2, (100u64 << 20).to_be_bytes());
    let chunk = vec![0x55u8; 1 << 20];
    let mut sent = socket.get_mut().write(&flood).unwrap();
    while sent < 100 << 20 {
        match socket.get_mut().write(&chunk) {
            Ok(n) => sent += n,
            Err(_) => break,
        }
    }
    eprintln!(
        "oversized: of 100 MB sent in one frame, the server took {:.1} MB before closing",
        sent as f64 / 1e6
    );
    assert!(sent < 100 << 20, "the server read a 100 MB frame");
    drop(socket);
    let mut stream = TcpStream::connect(&address).unwrap();
    write!(
        stream,
        "POST /?token={token} HTTP/1.1\r\nHost: x\r\nContent-Length: 1000000000\r\n\r\n"
    )
    .unwrap();
    let (answer, _) = read_to_close(&mut stream, IDLE + SLACK);
    assert!(
        answer.starts_with(b"HTTP/1.1 405"),
        "{}",
        String::from_utf8_lossy(&answer)
    );

    // Malformed frames, each closed with its code; malformed JSON answered, the page kept.
    let cases: [(&str, Vec<u8>, CloseCode); 5] = [
        ("unmasked", frame(0x81, b"{}", false), CloseCode::Protocol),
        ("reserved opcode", frame(0x83, b"{}", true), CloseCode::Protocol),
        (
            "continuation first",
            frame(0x80, b"{}", true),
            CloseCode::Protocol,
        ),
        (
            "invalid UTF-8",
            frame(0x81, &[0xff, 0xfe, 0xfd], true),
            CloseCode::Invalid,
        ),
        ("binary", frame(0x82, b"{}", true), CloseCode::Unsupported),
    ];
    for (what, bytes, expected) in cases {
        assert_eq!(close_code_for(&address, &token, &bytes), expected, "{what}");
    }
    let mut socket = page(&address, &token);
    let nested = "[".repeat(100_000);
    for text in [
        "[]",
        r#"{"id": 1e400, "type": "camera"}"#,
        r#"{"id": 1, "type": "camera", "eye": "x"}"#,
        &nested,
    ] {
        socket.send(Message::Text(text.into())).unwrap();
        loop {
            match receive(&mut socket) {
                Reply::Json(m) if m["type"] == "error" => break,
                _ => {}
            }
        }
    }
    drop(socket);

    // Paths outside the page: nothing but the embedded page, script and style is served.
    for path in [
        "/../../../../etc/passwd",
        "/%2e%2e/%2e%2e/etc/passwd",
        "/..%2f..%2f..%2fetc%2fpasswd",
        "//etc/passwd",
        "/viewer.js/../../Cargo.toml",
        "/%2e%2e%5c%2e%2e%5cCargo.toml",
        "/.%00./etc/passwd",
    ] {
        let (status, body) = get(&address, &format!("{path}?token={token}"));
        assert_eq!(status, 404, "{path}: {body}");
        assert!(!body.contains("root:") && !body.contains("[package]"), "{path}");
    }

    // Wrong tokens at a high rate: each answered 403.
    let start = Instant::now();
    for i in 0..1000 {
        let wrong = format!("{i:032x}");
        let status = match i % 4 {
            0 => open_page(&address, &wrong).err().unwrap(),
            1 => get(&address, &format!("/ws?token={wrong}")).0,
            2 => get(&address, "/").0,
            _ => get(&address, &format!("/?token={wrong}")).0,
        };
        assert_eq!(status, 403, "request {i}");
    }
    eprintln!(
        "wrong tokens: 1000 answered 403 at {:.0} a second",
        1000.0 / start.elapsed().as_secs_f64()
    );
    let attack = attack.elapsed();

    // The run went on, the good page was served throughout, and what the clients held is given back.
    std::thread::sleep(IDLE + IDLE / 3 + Duration::from_secs(1));
    let step_after = step.load(Ordering::Relaxed);
    let (rss_after, _, threads_after) = usage(pid);
    // The fewest descriptors over a second: the training run opens files of its own for a moment (its
    // checkpoint, its logs), while what a client left held would stay.
    let fds_after = (0..10)
        .map(|_| {
            std::thread::sleep(Duration::from_millis(100));
            usage(pid).1
        })
        .min()
        .unwrap_or(usize::MAX);
    stop.store(true, Ordering::Relaxed);
    let witness = witness.join().expect("the good page was served throughout");
    let before: Vec<Duration> = witness.latencies.iter().take(3).copied().collect();
    eprintln!(
        "over {:.0} s of attack the run went from step {step_before} to {step_after}; the good page got {} \
         frames, median latency {:?} (first three {:?}), longest {:?}; resident memory {} -> {} MB, descriptors \
         {fds_before} -> {fds_after}, threads {threads_before} -> {threads_after}",
        attack.as_secs_f64(),
        witness.latencies.len(),
        median(&witness.latencies),
        median(&before),
        witness.latencies.iter().max().unwrap(),
        rss_before / 1024,
        rss_after / 1024,
    );
    assert!(step_after > step_before, "the run stopped training");
    assert!(*witness.latencies.iter().max().unwrap() < Duration::from_secs(10));
    assert!(fds_after <= fds_before, "descriptors {fds_before} -> {fds_after}");
    assert!(
        threads_after <= threads_before,
        "threads {threads_before} -> {threads_after}"
    );
    assert!(
        rss_after < rss_before + 256 * 1024,
        "memory {rss_before} -> {rss_after} kB"
    );
}
