//! The HTTP and WebSocket API of `nerfjit view`, driven as a page would drive it (no browser): the token,
//! frames for camera requests, diagnostics and new frames for edits.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use serde_json::{json, Value};

use tungstenite::{Message, WebSocket};

mod hostile_clients;

/// A `nerfjit view` process, stopped when dropped.
struct Viewer {
    child: Child,
    /// `127.0.0.1:port`.
    address: String,
    token: String,
}

impl Drop for Viewer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Starts `nerfjit view SOURCE` on a free port and reads the URL it prints.
fn view(source: &str) -> Viewer {
    serve(&["view", source, "--port", "0"], Path::new("."))
}

/// Starts nerfjit with `args` (that serve a page on a free port) in `dir` and reads the URL it prints.
fn serve(args: &[&str], dir: &Path) -> Viewer {
    let mut child = Command::new(env!("CARGO_BIN_EXE_nerfjit"))
        .args(args)
        .current_dir(dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("nerfjit starts");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap_or_else(|| panic!("no URL in {line:?}"));
    let rest = url.trim_start_matches("http://");
    let (address, query) = rest.split_once("/?token=").expect("the URL carries a token");
    assert_eq!(query.len(), 32, "a 128-bit token in hex: {query}");
    Viewer {
        child,
        address: address.to_string(),
        token: query.to_string(),
    }
}

/// The status code and body of `GET path`.
fn get(address: &str, path: &str) -> (u16, String) {
    let mut stream = TcpStream::connect(address).unwrap();
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {address}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    let status = response.split_whitespace().nth(1).unwrap().parse().unwrap();
    let body = response.split_once("\r\n\r\n").map_or("", |(_, b)| b).to_string();
    (status, body)
}

type Socket = WebSocket<TcpStream>;

fn connect(viewer: &Viewer, token: &str) -> Result<Socket, tungstenite::Error> {
    let stream = TcpStream::connect(&viewer.address).unwrap();
    stream.set_read_timeout(Some(Duration::from_secs(120))).unwrap();
    let url = format!("ws://{}/ws?token={token}", viewer.address);
    tungstenite::client(url.as_str(), stream)
        .map(|(socket, _)| socket)
        .map_err(|e| match e {
            tungstenite::HandshakeError::Failure(e) => e,
            tungstenite::HandshakeError::Interrupted(_) => panic!("a blocking handshake is not interrupted"),
        })
}

/// One message of the server: JSON, a frame's header and decoded image, or an exported file's header and
/// bytes.
enum Reply {
    Json(Value),
    Frame(Value, image::RgbImage),
    File(Value, Vec<u8>),
}

fn receive(socket: &mut Socket) -> Reply {
    loop {
        match socket.read().expect("the server answers") {
            Message::Text(text) => return Reply::Json(serde_json::from_str(text.as_str()).unwrap()),
            Message::Binary(bytes) => {
                let length = u32::from_le_bytes(bytes[..4].try_into().unwrap()) as usize;
                let header: Value = serde_json::from_slice(&bytes[4..4 + length]).unwrap();
                if header["type"] == "file" {
                    return Reply::File(header, bytes[4 + length..].to_vec());
                }
                let format = match header["format"].as_str() {
                    Some("png") => image::ImageFormat::Png,
                    Some("jpeg") => image::ImageFormat::Jpeg,
                    other => panic!("unknown frame format {other:?}"),
                };
                let picture = image::load_from_memory_with_format(&bytes[4 + length..], format)
                    .expect("the frame decodes")
                    .to_rgb8();
                return Reply::Frame(header, picture);
            }
            _ => {}
        }
    }
}

/// The next JSON message, failing on a frame.
fn json_message(socket: &mut Socket) -> Value {
    match receive(socket) {
        Reply::Json(v) => v,
        Reply::Frame(header, _) | Reply::File(header, _) => {
            panic!("expected a JSON message, got {header}")
        }
    }
}

/// Frames up to the full-size one, checking each is of the request; returns the headers and the last image.
fn frames_until_final(socket: &mut Socket, camera_id: u64) -> (Vec<Value>, image::RgbImage) {
    let mut headers = Vec::new();
    loop {
        match receive(socket) {
            Reply::Frame(header, picture) => {
                assert_eq!(header["camera_id"], camera_id);
                assert_eq!(
                    picture.dimensions(),
                    (
                        header["width"].as_u64().unwrap() as u32,
                        header["height"].as_u64().unwrap() as u32
                    )
                );
                let last = header["final"] == true;
                headers.push(header);
                if last {
                    return (headers, picture);
                }
            }
            Reply::Json(v) | Reply::File(v, _) => panic!("expected a frame, got {v}"),
        }
    }
}

fn send(socket: &mut Socket, message: Value) {
    socket.send(Message::Text(message.to_string().into())).unwrap();
}

/// The hello, scene and (empty) diagnostics a page gets first.
fn opening(socket: &mut Socket) -> (Value, Value) {
    let hello = json_message(socket);
    assert_eq!(hello["type"], "hello");
    let scene = json_message(socket);
    assert_eq!(scene["type"], "scene", "{scene}");
    let diagnostics = json_message(socket);
    assert_eq!(diagnostics["type"], "diagnostics");
    assert_eq!(diagnostics["items"], json!([]));
    (hello, scene)
}

fn camera_request(id: u64, camera: &Value, width: u32, height: u32, layer: &str) -> Value {
    json!({
        "type": "camera", "id": id, "eye": camera["eye"], "target": camera["target"], "up": camera["up"],
        "focal": camera["focal"], "width": width, "height": height, "layer": layer,
    })
}

/// How much the pixels of an image vary (0 for a blank one).
fn spread(picture: &image::RgbImage) -> f64 {
    let values: Vec<f64> = picture
        .pixels()
        .map(|p| f64::from(p.0[0]) + f64::from(p.0[1]))
        .collect();
    let mean = values.iter().sum::<f64>() / values.len() as f64;
    (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / values.len() as f64).sqrt()
}

fn mean_difference(a: &image::RgbImage, b: &image::RgbImage) -> f64 {
    let total: f64 = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).abs())
        .sum();
    total / a.as_raw().len() as f64
}

#[test]
fn nothing_answers_without_the_token() {
    let viewer = view("examples/showcase.sdf");
    let (status, page) = get(&viewer.address, &format!("/?token={}", viewer.token));
    assert_eq!(status, 200);
    assert!(page.contains("<canvas"), "{page}");
    assert_eq!(get(&viewer.address, "/").0, 403);
    let wrong = format!("/?token={}", "0".repeat(32));
    assert_eq!(get(&viewer.address, &wrong).0, 403);
    for token in ["", "0123", &"0".repeat(32)] {
        match connect(&viewer, token) {
            Err(tungstenite::Error::Http(response)) => assert_eq!(response.status(), 403),
            Err(e) => panic!("expected 403, got {e}"),
            Ok(_) => panic!("a socket opened with token {token:?}"),
        }
    }
}

#[test]
fn a_camera_gets_a_coarse_frame_then_finer_ones_up_to_the_full_size() {
    let viewer = view("examples/showcase.sdf");
    let mut socket = connect(&viewer, &viewer.token).unwrap();
    let (hello, scene) = opening(&mut socket);
    assert_eq!(hello["name"], "examples/showcase.sdf");
    assert!(hello["source"].as_str().unwrap().contains("smooth_union"));
    assert_eq!(scene["kind"], "surface");
    assert_eq!(scene["layers"], json!(["color", "depth", "normals"]));
    assert_eq!(scene["cameras"].as_array().unwrap().len(), 36);
    assert_eq!(scene["consts"], json!([{"name": "k", "value": 0.25}]));
    let camera = &scene["cameras"][0];
    for (id, layer) in [(1, "color"), (2, "depth"), (3, "normals")] {
        send(&mut socket, camera_request(id, camera, 160, 120, layer));
        let (headers, picture) = frames_until_final(&mut socket, id);
        assert_eq!(picture.dimensions(), (160, 120));
        assert!(
            spread(&picture) > 10.0,
            "{layer}: the scene shows, not a blank frame"
        );
        let widths: Vec<u64> = headers.iter().map(|h| h["width"].as_u64().unwrap()).collect();
        assert!(widths.windows(2).all(|w| w[0] < w[1]), "sizes grow: {widths:?}");
        assert!(headers
            .iter()
            .all(|h| (h["format"] == "png") == (h["final"] == true)));
    }
}

#[test]
fn an_edit_answers_with_diagnostics_at_the_mistake_or_with_a_new_frame() {
    let viewer = view("examples/showcase.sdf");
    let mut socket = connect(&viewer, &viewer.token).unwrap();
    let (hello, scene) = opening(&mut socket);
    let source = hello["source"].as_str().unwrap().to_string();
    send(
        &mut socket,
        camera_request(1, &scene["cameras"][0], 96, 96, "color"),
    );
    let (_, before) = frames_until_final(&mut socket, 1);

    let broken = source.replacen(
        "sphere(p - [0, 0.95, 0], 0.35)",
        "spere(p - [0, 0.95, 0], 0.35)",
        1,
    );
    assert_ne!(broken, source);
    let line = broken.lines().position(|l| l.contains("spere(")).unwrap() + 1;
    let column = broken.lines().nth(line - 1).unwrap().find("spere").unwrap() + 1;
    send(&mut socket, json!({"type": "source", "id": 2, "text": broken}));
    let diagnostics = json_message(&mut socket);
    assert_eq!(diagnostics["type"], "diagnostics");
    assert_eq!(diagnostics["source_id"], 2);
    let first = &diagnostics["items"][0];
    assert!(first["message"].as_str().unwrap().contains("spere"), "{first}");
    assert_eq!(first["at"]["line"], line, "{first}");
    assert_eq!(first["at"]["column"], column, "{first}");
    assert_eq!(first["hint"], "did you mean 'sphere'?", "{first}");
    // The last scene that compiled is rendered again for the same camera.
    let (_, kept) = frames_until_final(&mut socket, 1);
    assert_eq!(mean_difference(&kept, &before), 0.0);

    let wider = source.replacen("const k = 0.25", "const k = 0.6", 1);
    send(&mut socket, json!({"type": "source", "id": 3, "text": wider}));
    let scene = json_message(&mut socket);
    assert_eq!(scene["type"], "scene");
    assert_eq!(scene["consts"], json!([{"name": "k", "value": 0.6}]));
    assert_eq!(json_message(&mut socket)["items"], json!([]));
    let (headers, after) = frames_until_final(&mut socket, 1);
    assert!(headers.iter().all(|h| h["source_id"] == 3));
    assert!(
        mean_difference(&after, &before) > 0.5,
        "a wider blend changes the picture"
    );
}

fn scratch(name: &str) -> crate::common::Scratch {
    crate::common::scratch("view", name)
}

#[test]
fn a_volume_field_renders_color_and_depth_and_bad_requests_are_answered() {
    let dir = scratch("volume");
    let script = dir.join("ball.sdf");
    std::fs::write(
        &script,
        "fn density(p: vec3) -> f32 = 30 * relu(1 - length(p))\n\
         fn color(p: vec3) -> vec3 = [1, 0.5, 0.1]\n",
    )
    .unwrap();
    let viewer = view(script.to_str().unwrap());
    let mut socket = connect(&viewer, &viewer.token).unwrap();
    let (_, scene) = opening(&mut socket);
    assert_eq!(scene["kind"], "volume");
    assert_eq!(scene["layers"], json!(["color", "depth"]));
    let camera = json!({"eye": [0, 0, -4], "target": [0, 0, 0], "up": [0, 1, 0], "focal": 1.5});
    for (id, layer) in [(1, "color"), (2, "depth")] {
        send(&mut socket, camera_request(id, &camera, 48, 40, layer));
        let (_, picture) = frames_until_final(&mut socket, id);
        let (center, corner) = (picture.get_pixel(24, 20).0, picture.get_pixel(0, 0).0);
        assert_ne!(center, corner, "{layer}: the ball differs from the background");
    }
    send(&mut socket, camera_request(3, &camera, 48, 40, "normals"));
    let error = json_message(&mut socket);
    assert_eq!(error["type"], "error");
    assert!(error["message"].as_str().unwrap().contains("surfaces"), "{error}");

    let bad = [
        (
            json!({"type": "camera", "id": 4}),
            "'eye' must be three finite numbers",
        ),
        (json!({"type": "zoom", "id": 5}), "unknown request type"),
        (json!({"type": "source"}), "'id'"),
        (
            camera_request(6, &camera, 100_000, 40, "color"),
            "'width' must be a whole number from 1 to 4096",
        ),
    ];
    for (request, expected) in bad {
        send(&mut socket, request);
        let error = json_message(&mut socket);
        assert_eq!(error["type"], "error");
        assert!(error["message"].as_str().unwrap().contains(expected), "{error}");
    }
    socket.send(Message::Text("not json".into())).unwrap();
    assert!(json_message(&mut socket)["message"]
        .as_str()
        .unwrap()
        .contains("not JSON"));
}

/// Messages up to the first that `stop` accepts (returned last); frames are returned as their headers.
fn until(socket: &mut Socket, stop: impl Fn(&Value) -> bool) -> Vec<Value> {
    let mut seen = Vec::new();
    loop {
        let message = match receive(socket) {
            Reply::Json(v) => v,
            Reply::Frame(header, _) | Reply::File(header, _) => header,
        };
        let done = stop(&message);
        seen.push(message);
        if done {
            return seen;
        }
    }
}

fn progress_steps(messages: &[Value]) -> Vec<u64> {
    messages
        .iter()
        .filter(|m| m["type"] == "progress")
        .map(|m| m["record"]["step"].as_u64().unwrap())
        .collect()
}

#[test]
fn a_training_run_streams_its_progress_and_frames_of_its_params_and_pauses() {
    let dir = scratch("live");
    crate::common::make_views(&dir);
    std::fs::write(dir.join("train.sdf"), crate::common::trainer_with(50_000, "")).unwrap();
    let viewer = serve(&["run", "train.sdf", "--view", "--port", "0"], &dir);
    let mut socket = connect(&viewer, &viewer.token).unwrap();
    let hello = json_message(&mut socket);
    assert_eq!(hello["training"]["paused"], false, "{hello}");
    assert!(hello["source"].as_str().unwrap().contains("train {"));
    let camera = json!({"eye": [-2.5, 0.3, 0.0], "target": [0, 0, 0], "up": [0, 1, 0], "focal": 1.0});
    send(&mut socket, camera_request(1, &camera, 40, 40, "color"));
    // Records every 10 steps, and frames of ever newer params (the renderer is woken by each copy).
    let seen = until(&mut socket, |m| {
        m["type"] == "frame" && m["params_step"].as_u64().is_some_and(|s| s >= 20)
    });
    let scene = seen
        .iter()
        .find(|m| m["type"] == "scene")
        .expect("the scene comes first");
    let labels: Vec<&str> = scene["cameras"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["label"].as_str().unwrap())
        .collect();
    assert_eq!(
        labels,
        [
            "data view 1 of 4",
            "data view 2 of 4",
            "data view 3 of 4",
            "data view 4 of 4"
        ]
    );
    let steps = progress_steps(&seen);
    assert!(
        steps.len() >= 2 && steps.windows(2).all(|w| w[0] < w[1]),
        "{steps:?}"
    );
    assert!(steps.iter().all(|s| s % 10 == 0));
    let record = &seen.iter().find(|m| m["type"] == "progress").unwrap()["record"];
    for key in ["loss", "psnr", "steps_per_s", "eta_seconds", "train_seconds"] {
        assert!(
            record[key].as_f64().is_some_and(f64::is_finite),
            "{key} in {record}"
        );
    }
    assert_eq!(record["steps"], 50_000);

    // Paused, the run stops: no record comes between two requests answered 0.8 s apart (a request the
    // run refuses serves as the ping).
    send(&mut socket, json!({"type": "pause", "id": 2, "paused": true}));
    let ping = |socket: &mut Socket, id: u64| {
        std::thread::sleep(Duration::from_millis(800));
        send(
            socket,
            json!({"type": "source", "id": id, "text": "fn f() -> f32 = 1"}),
        );
        let seen = until(socket, |m| m["type"] == "error");
        let error = seen.last().unwrap()["message"].as_str().unwrap().to_string();
        assert!(error.contains("being trained"), "{error}");
        progress_steps(&seen)
    };
    let before_pause = ping(&mut socket, 3);
    assert_eq!(ping(&mut socket, 4), Vec::<u64>::new(), "a paused run goes on");
    // Resumed, it goes on.
    let last = before_pause.into_iter().chain(steps).max().unwrap();
    send(&mut socket, json!({"type": "pause", "id": 5, "paused": false}));
    until(&mut socket, |m| {
        m["type"] == "progress" && m["record"]["step"].as_u64().unwrap() > last
    });
    drop(viewer);
}

#[test]
fn the_export_buttons_get_an_orbit_video_a_mesh_and_a_checkpoint() {
    let viewer = view("examples/torus.sdf");
    let mut socket = connect(&viewer, &viewer.token).unwrap();
    let (_, scene) = opening(&mut socket);
    let camera = &scene["cameras"][0];
    let export = |what: &str, id: u64| {
        json!({"type": "export", "id": id, "what": what, "eye": camera["eye"], "target": camera["target"],
               "up": camera["up"], "focal": camera["focal"]})
    };
    send(&mut socket, export("video", 1));
    let Reply::File(header, video) = receive(&mut socket) else {
        panic!("expected a file")
    };
    assert_eq!(header["name"], "torus-orbit.mp4");
    assert_eq!(header["mime"], "video/mp4");
    assert_eq!(&video[4..8], b"ftyp", "an MP4 file");
    send(&mut socket, export("mesh", 2));
    let Reply::File(header, mesh) = receive(&mut socket) else {
        panic!("expected a file")
    };
    assert_eq!(header["name"], "torus.ply");
    assert!(
        mesh.starts_with(b"ply\nformat binary_little_endian"),
        "a binary PLY file"
    );
    // A checkpoint of the shown params, with the script, that the CLI meshes.
    send(&mut socket, export("checkpoint", 3));
    let Reply::File(header, checkpoint) = receive(&mut socket) else {
        panic!("expected a file")
    };
    assert_eq!(header["name"], "torus.ckpt.safetensors");
    let dir = scratch("export");
    std::fs::write(dir.join("torus.ckpt.safetensors"), checkpoint).unwrap();
    let (ok, _, err) = crate::common::run(
        &dir,
        &[
            "mesh",
            "torus.ckpt.safetensors",
            "--res",
            "32",
            "--bounds",
            "1.5",
            "--out",
            "torus.ply",
        ],
    );
    assert!(ok, "{err}");
    assert!(std::fs::metadata(dir.join("torus.ply")).unwrap().len() > 1000);
    send(&mut socket, export("gltf", 4));
    let error = json_message(&mut socket);
    assert!(
        error["message"]
            .as_str()
            .unwrap()
            .contains("cannot export 'gltf'"),
        "{error}"
    );
}

#[test]
fn a_checkpoint_is_shown_with_its_trained_params_and_an_edit_that_changes_them_says_so() {
    let dir = scratch("checkpoint");
    crate::common::make_views(&dir);
    std::fs::write(dir.join("train.sdf"), crate::common::trainer_with(20, "")).unwrap();
    let (ok, _, err) = crate::common::run(&dir, &["run", "train.sdf"]);
    assert!(ok, "{err}");
    let checkpoint = dir.join("train.ckpt.safetensors");
    let viewer = view(checkpoint.to_str().unwrap());
    let mut socket = connect(&viewer, &viewer.token).unwrap();
    let (hello, scene) = opening(&mut socket);
    assert_eq!(hello["checkpoint"], true);
    assert!(hello["name"].as_str().unwrap().ends_with("train.sdf"), "{hello}");
    assert_eq!(scene["kind"], "volume");
    assert_eq!(scene["note"], Value::Null);
    let camera = json!({"eye": [-2.5, 0.3, 0.0], "target": [0, 0, 0], "up": [0, 1, 0], "focal": 1.0});
    send(&mut socket, camera_request(1, &camera, 40, 40, "color"));
    let (_, trained) = frames_until_final(&mut socket, 1);
    // Another param: the script's own initial values are shown, and the page is told.
    let source = hello["source"].as_str().unwrap();
    let edited = format!("param extra: f32 = 1\n{source}");
    send(&mut socket, json!({"type": "source", "id": 2, "text": edited}));
    let scene = json_message(&mut socket);
    assert!(
        scene["note"]
            .as_str()
            .unwrap()
            .contains("differ from the checkpoint's"),
        "{scene}"
    );
    assert_eq!(json_message(&mut socket)["items"], json!([]));
    let (_, initial) = frames_until_final(&mut socket, 1);
    assert!(
        mean_difference(&trained, &initial) > 0.5,
        "trained and initial params differ"
    );
}

#[test]
fn a_bake_is_drawn_at_full_size_as_the_cli_renders_it_with_its_script_read_only() {
    let dir = scratch("bake");
    crate::common::make_views(&dir);
    std::fs::write(dir.join("train.sdf"), crate::common::trainer_with(200, "")).unwrap();
    let (ok, _, err) = crate::common::run(&dir, &["run", "train.sdf"]);
    assert!(ok, "{err}");
    let bake = [
        "bake",
        "train.ckpt.safetensors",
        "--cameras",
        "cams.json",
        "--size",
        "40",
        "--out",
        "box.bake",
    ];
    let (ok, _, err) = crate::common::run(&dir, &bake);
    assert!(ok, "{err}");
    let viewer = serve(&["view", "box.bake", "--port", "0"], &dir);
    let mut socket = connect(&viewer, &viewer.token).unwrap();
    let (hello, scene) = opening(&mut socket);
    assert_eq!(hello["bake"]["path"], "box.bake", "{hello}");
    assert!(hello["bake"]["splats"].as_u64().unwrap() > 50, "{hello}");
    assert!(
        hello["source"].as_str().unwrap().contains("train {"),
        "the checkpoint's script: {hello}"
    );
    assert_eq!(scene["kind"], "splats");
    assert_eq!(scene["layers"], json!(["color", "depth"]));
    let (eye, side) = ([-2.5, 0.8, 0.6], 48);
    let camera = json!({"eye": eye, "target": [0, 0, 0], "up": [0, 1, 0], "focal": 1.0});
    for (id, layer) in [(1, "color"), (2, "depth")] {
        send(&mut socket, camera_request(id, &camera, side, side, layer));
        let (headers, picture) = frames_until_final(&mut socket, id);
        // No coarse frames: the full size at once as JPEG, then (the camera resting) as PNG.
        let formats: Vec<&str> = headers.iter().map(|h| h["format"].as_str().unwrap()).collect();
        assert_eq!(formats, ["jpeg", "png"], "{layer}");
        assert!(headers.iter().all(|h| h["width"] == side && h["height"] == side));
        assert!(
            spread(&picture) > 10.0,
            "{layer}: the box shows, not the background alone"
        );
        if layer == "color" {
            // The CLI's render of the bake from the same camera, pixel for pixel.
            let path = format!("look_at(eye: {eye:?}, at: [0, 0, 0], up: [0, 1, 0], focal: 1.0)");
            let args = [
                "render", "box.bake", "--path", &path, "--size", "48", "--out", "cli",
            ];
            let (ok, _, err) = crate::common::run(&dir, &args);
            assert!(ok, "{err}");
            let cli = image::open(dir.join("cli/view.png")).unwrap().to_rgb8();
            assert_eq!(mean_difference(&picture, &cli), 0.0);
        }
    }
    send(
        &mut socket,
        json!({"type": "source", "id": 3, "text": "fn density(p: vec3) -> f32 = 1"}),
    );
    let refused = json_message(&mut socket);
    assert_eq!(refused["type"], "error");
    assert!(
        refused["message"].as_str().unwrap().contains("read-only"),
        "{refused}"
    );
}
