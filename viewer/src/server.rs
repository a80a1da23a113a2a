//! The viewer's HTTP server: the page (HTML, JS and CSS embedded in the binary) and a WebSocket per open
//! page, each with a renderer thread of its own. Nothing answers without the access token.

use std::collections::HashMap;
use std::sync::Arc;

use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use glam::Vec3;
use serde_json::{json, Value};

use super::export::Export;
use super::mailbox::{ExportRequest, FrameRequest, Mailbox};
use super::renderer::{self, Outgoing, MAX_SIDE};
use super::scene::{Layer, ViewCamera};
use super::{Document, Live};
use nerfjit::failure::{Failure, Result};

const PAGE: &str = include_str!("page/index.html");
const SCRIPT: &str = include_str!("page/viewer.js");
const STYLE: &str = include_str!("page/viewer.css");

/// The longest script a page may send, in bytes.
const MAX_SOURCE_BYTES: usize = 1 << 20;

#[derive(Clone)]
struct Shared {
    document: Arc<Document>,
    token: Arc<str>,
    live: Option<Arc<Live>>,
}

/// Serves the page on `listener` until the process ends; with a training run, pages follow it.
pub fn serve(
    listener: std::net::TcpListener,
    document: Document,
    token: String,
    live: Option<Arc<Live>>,
) -> Result<()> {
    let failed = |e: std::io::Error| Failure::Message(format!("the viewer's server failed: {e}"));
    listener.set_nonblocking(true).map_err(failed)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .map_err(failed)?;
    let shared = Shared {
        document: Arc::new(document),
        token: token.into(),
        live,
    };
    let app = Router::new()
        .route("/", get(page))
        .route("/viewer.js", get(|| async { asset("text/javascript", SCRIPT) }))
        .route("/viewer.css", get(|| async { asset("text/css", STYLE) }))
        .route("/ws", get(socket))
        .route("/favicon.ico", get(|| async { StatusCode::NO_CONTENT }))
        .with_state(shared);
    runtime
        .block_on(async move {
            let listener = tokio::net::TcpListener::from_std(listener)?;
            axum::serve(listener, app).await
        })
        .map_err(failed)
}

/// Whether the query carries the token (compared in time independent of where they differ).
fn authorized(query: &HashMap<String, String>, token: &str) -> bool {
    query.get("token").is_some_and(|given| {
        given.len() == token.len() && given.bytes().zip(token.bytes()).fold(0, |d, (a, b)| d | (a ^ b)) == 0
    })
}

fn forbidden() -> Response {
    (
        StatusCode::FORBIDDEN,
        "nerfjit view: this address needs the token in the URL that `nerfjit view` printed\n",
    )
        .into_response()
}

fn asset(content_type: &'static str, body: &'static str) -> Response {
    ([(header::CONTENT_TYPE, content_type)], body).into_response()
}

async fn page(State(shared): State<Shared>, Query(query): Query<HashMap<String, String>>) -> Response {
    if !authorized(&query, &shared.token) {
        return forbidden();
    }
    (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        PAGE,
    )
        .into_response()
}

async fn socket(
    State(shared): State<Shared>,
    Query(query): Query<HashMap<String, String>>,
    upgrade: WebSocketUpgrade,
) -> Response {
    if !authorized(&query, &shared.token) {
        return forbidden();
    }
    upgrade
        .max_message_size(2 * MAX_SOURCE_BYTES)
        .on_upgrade(move |socket| session(socket, shared.document, shared.live))
}

/// One open page: its requests go to its renderer thread, the renderer's messages to the page, and a
/// training run's progress records to the page as they come.
async fn session(mut socket: WebSocket, document: Arc<Document>, live: Option<Arc<Live>>) {
    let mailbox = Arc::new(Mailbox::default());
    let (outbox, mut outgoing) = tokio::sync::mpsc::unbounded_channel();
    let mut progress = live.as_ref().map(|l| l.subscribe());
    let hello = json!({
        "type": "hello",
        "name": document.name,
        "source": document.source,
        "checkpoint": document.trained.is_some(),
        "training": live.as_ref().map(|l| json!({"history": l.history(), "paused": l.paused()})),
    });
    if socket
        .send(Message::Text(hello.to_string().into()))
        .await
        .is_err()
    {
        return;
    }
    if let Some(live) = &live {
        live.listen(&mailbox);
    }
    let worker = {
        let mailbox = Arc::clone(&mailbox);
        let live = live.clone();
        std::thread::Builder::new()
            .name("nerfjit view".into())
            .stack_size(nerfjit::WORK_STACK_BYTES)
            .spawn(move || {
                nerfjit_runtime::flush_denormals();
                renderer::serve(&document, &mailbox, &outbox, live.as_deref());
            })
    };
    if let Err(e) = worker {
        let message = json!({"type": "error", "message": format!("cannot start a renderer: {e}")});
        let _ = socket.send(Message::Text(message.to_string().into())).await;
        return;
    }
    loop {
        tokio::select! {
            incoming = socket.recv() => match incoming {
                Some(Ok(Message::Text(text))) => {
                    if let Err(message) = post(&text, &mailbox, live.as_deref()) {
                        let error = json!({"type": "error", "message": message});
                        if socket.send(Message::Text(error.to_string().into())).await.is_err() {
                            break;
                        }
                    }
                }
                Some(Ok(Message::Close(_))) | Some(Err(_)) | None => break,
                Some(Ok(_)) => {}
            },
            Some(record) = next_record(&mut progress) => {
                let message = json!({"type": "progress", "record": record});
                if socket.send(Message::Text(message.to_string().into())).await.is_err() {
                    break;
                }
            }
            message = outgoing.recv() => {
                let message = match message {
                    Some(Outgoing::Text(text)) => Message::Text(text.into()),
                    Some(Outgoing::Frame(bytes)) => Message::Binary(bytes.into()),
                    // The renderer has ended (it panicked: its message is on stderr).
                    None => break,
                };
                if socket.send(message).await.is_err() {
                    break;
                }
            }
        }
    }
    mailbox.close();
}

/// The next progress record of a training run; never, without one (or once it has ended).
async fn next_record(progress: &mut Option<tokio::sync::watch::Receiver<Value>>) -> Option<Value> {
    if let Some(receiver) = progress {
        if receiver.changed().await.is_ok() {
            return Some(receiver.borrow_and_update().clone());
        }
    }
    std::future::pending().await
}

/// Reads one request of the page and posts it for the renderer (or, to pause or resume, to the training
/// run); says what is wrong with a bad one.
fn post(text: &str, mailbox: &Mailbox, live: Option<&Live>) -> std::result::Result<(), String> {
    let request: Value =
        serde_json::from_str(text).map_err(|e| format!("a request that is not JSON: {e}"))?;
    let id = request["id"]
        .as_u64()
        .ok_or("a request needs a whole number 'id'")?;
    match request["type"].as_str() {
        Some("source") if live.is_some() => {
            return Err("the script is being trained: edit it once the run has ended".into());
        }
        Some("pause") => {
            let live = live.ok_or("only a training run (nerfjit run --view) can be paused")?;
            live.set_paused(
                request["paused"]
                    .as_bool()
                    .ok_or("a 'pause' request needs 'paused': true or false")?,
            );
        }
        Some("source") => {
            let source = request["text"]
                .as_str()
                .ok_or("a 'source' request needs its 'text'")?;
            if source.len() > MAX_SOURCE_BYTES {
                return Err(format!("the script is longer than {MAX_SOURCE_BYTES} bytes"));
            }
            mailbox.post_source(id, source.to_string());
        }
        Some("camera") => mailbox.post_frame(frame_request(id, &request)?),
        Some("export") => {
            let name = request["what"].as_str().unwrap_or_default();
            let what = Export::parse(name)
                .ok_or_else(|| format!("cannot export '{name}': video, mesh or checkpoint"))?;
            let view = view_camera(&request)?;
            mailbox.post_export(ExportRequest { id, what, view });
        }
        other => {
            return Err(format!(
                "unknown request type {other:?}: 'camera', 'source', 'export' or 'pause'"
            ))
        }
    }
    Ok(())
}

/// The camera of a request: `eye`, `target`, `up` and `focal`.
fn view_camera(request: &Value) -> std::result::Result<ViewCamera, String> {
    let vector = |key: &str| -> std::result::Result<Vec3, String> {
        let values: Option<Vec<f32>> = request[key]
            .as_array()
            .filter(|a| a.len() == 3)
            .and_then(|a| a.iter().map(|x| x.as_f64().map(|x| x as f32)).collect());
        values
            .filter(|v| v.iter().all(|x| x.is_finite()))
            .map(|v| Vec3::from_slice(&v))
            .ok_or_else(|| format!("camera '{key}' must be three finite numbers"))
    };
    let (eye, target, up) = (vector("eye")?, vector("target")?, vector("up")?);
    let focal = request["focal"]
        .as_f64()
        .filter(|f| f.is_finite() && *f > 0.0)
        .ok_or("camera 'focal' must be a positive number")? as f32;
    Ok(ViewCamera {
        eye,
        target,
        up,
        focal,
    })
}

fn frame_request(id: u64, request: &Value) -> std::result::Result<FrameRequest, String> {
    let side = |key: &str| -> std::result::Result<u32, String> {
        request[key]
            .as_u64()
            .filter(|n| (1..=u64::from(MAX_SIDE)).contains(n))
            .map(|n| n as u32)
            .ok_or_else(|| format!("'{key}' must be a whole number from 1 to {MAX_SIDE}"))
    };
    let view = view_camera(request)?;
    let layer = request["layer"].as_str().unwrap_or("color");
    Ok(FrameRequest {
        id,
        view,
        width: side("width")?,
        height: side("height")?,
        layer: Layer::parse(layer)
            .ok_or_else(|| format!("unknown layer '{layer}': color, depth or normals"))?,
    })
}
