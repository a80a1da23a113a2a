//! The viewer's HTTP server: the page (HTML, JS and CSS embedded in the binary) and a WebSocket per open
//! page, each with a renderer thread of its own. Nothing answers without the access token, and no client
//! holds more than [`Limits`] gives it: connections past the limit are answered 503 at once, a request's
//! head must arrive within the idle time, a page that neither sends nor answers the server's pings for that
//! long (or does not read what is sent to it) is closed, and a WebSocket message is at most 2 MB.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::{close_code, CloseFrame, Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use glam::Vec3;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use serde_json::{json, Value};
use tokio::io::AsyncWriteExt;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

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

/// The largest WebSocket message (and frame) a page may send, in bytes: a script and its JSON.
const MAX_MESSAGE_BYTES: usize = 2 * MAX_SOURCE_BYTES;

/// How much the server gives its clients (`--max-connections`, `--max-pages`, `--idle-timeout`).
#[derive(Clone, Copy, Debug)]
pub struct Limits {
    /// Open HTTP connections at once (a page's WebSocket counts among the pages instead); the next is
    /// answered 503 and closed.
    pub connections: usize,
    /// Open pages (WebSockets, each with a renderer thread) at once; the next is answered 503.
    pub pages: usize,
    /// How long a request's head may take to arrive, a page may stay silent (it answers the server's
    /// pings, sent a third of this apart) and a message to a page may wait to be read.
    pub idle: Duration,
}

impl Default for Limits {
    fn default() -> Limits {
        Limits {
            connections: 256,
            pages: 8,
            idle: Duration::from_secs(30),
        }
    }
}

#[derive(Clone)]
struct Shared {
    document: Arc<Document>,
    token: Arc<str>,
    live: Option<Arc<Live>>,
    /// The pages that may still open.
    pages: Arc<Semaphore>,
    limits: Limits,
}

/// Serves the page on `listener` until the process ends; with a training run, pages follow it.
pub fn serve(
    listener: std::net::TcpListener,
    document: Document,
    token: String,
    live: Option<Arc<Live>>,
    limits: Limits,
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
        pages: Arc::new(Semaphore::new(limits.pages)),
        limits,
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
            accept(listener, app, limits).await
        })
        .map_err(failed)
}

/// Accepts connections for ever: each within the limit is served on a task of its own; one past it is
/// answered 503 and closed. Failing accepts (out of file descriptors, say) are retried after a pause.
async fn accept(listener: tokio::net::TcpListener, app: Router, limits: Limits) -> std::io::Result<()> {
    let connections = Arc::new(Semaphore::new(limits.connections));
    loop {
        let stream = match listener.accept().await {
            Ok((stream, _)) => stream,
            Err(_) => {
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        match Arc::clone(&connections).try_acquire_owned() {
            Ok(permit) => {
                tokio::spawn(connection(stream, app.clone(), limits.idle, permit));
            }
            Err(_) => {
                tokio::spawn(refuse(stream, limits.connections));
            }
        }
    }
}

/// Serves one connection (HTTP/1.1, upgraded to a WebSocket for a page) while it holds `_permit`.
async fn connection(
    stream: tokio::net::TcpStream,
    app: Router,
    idle: Duration,
    _permit: OwnedSemaphorePermit,
) {
    let service = TowerToHyperService::new(app);
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(TokioTimer::new()).header_read_timeout(idle);
    // Errors here are the client's (a broken or slow request): the connection ends, nothing else does.
    let _ = http
        .serve_connection(TokioIo::new(stream), service)
        .with_upgrades()
        .await;
}

/// Answers a connection past the limit with 503 (or gives up on a client that will not read it).
async fn refuse(mut stream: tokio::net::TcpStream, limit: usize) {
    let body =
        format!("nerfjit view: {limit} connections are open, the most it serves at once; try again later\n");
    let response = format!(
        "HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
        body.len()
    );
    let _ = tokio::time::timeout(Duration::from_secs(1), stream.write_all(response.as_bytes())).await;
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
    upgrade: std::result::Result<WebSocketUpgrade, WebSocketUpgradeRejection>,
) -> Response {
    if !authorized(&query, &shared.token) {
        return forbidden();
    }
    let upgrade = match upgrade {
        Ok(upgrade) => upgrade,
        Err(rejection) => return rejection.into_response(),
    };
    let Ok(page) = Arc::clone(&shared.pages).try_acquire_owned() else {
        return (
            StatusCode::SERVICE_UNAVAILABLE,
            format!(
                "nerfjit view: {} pages are open, the most it serves at once (--max-pages); close one\n",
                shared.limits.pages
            ),
        )
            .into_response();
    };
    let idle = shared.limits.idle;
    upgrade
        .max_message_size(MAX_MESSAGE_BYTES)
        .max_frame_size(MAX_MESSAGE_BYTES)
        .on_upgrade(move |socket| async move {
            let page = Page {
                socket,
                idle,
                _permit: page,
            };
            session(page, shared.document, shared.live).await;
        })
}

/// An open page's WebSocket: sends that give up on a page that does not read them within the idle time.
struct Page {
    socket: WebSocket,
    idle: Duration,
    /// The page's place among the open pages.
    _permit: OwnedSemaphorePermit,
}

impl Page {
    /// Sends `message`; false when the page has gone or has not read for the idle time.
    async fn send(&mut self, message: Message) -> bool {
        matches!(
            tokio::time::timeout(self.idle, self.socket.send(message)).await,
            Ok(Ok(()))
        )
    }

    /// Sends a JSON message.
    async fn send_json(&mut self, message: &Value) -> bool {
        self.send(Message::Text(message.to_string().into())).await
    }

    /// Closes the socket with `code` and `reason` (if the page still reads).
    async fn close(&mut self, code: u16, reason: &str) {
        let frame = CloseFrame {
            code,
            reason: reason.into(),
        };
        self.send(Message::Close(Some(frame))).await;
    }
}

/// The WebSocket close code and reason for a broken message from a page; none when the connection
/// itself failed (there is nobody to tell).
fn close_for(error: axum::Error) -> Option<(u16, String)> {
    let error = error.into_inner().downcast::<tungstenite::Error>().ok()?;
    let code = match *error {
        tungstenite::Error::Capacity(_) => close_code::SIZE,
        tungstenite::Error::Utf8(_) => close_code::INVALID,
        tungstenite::Error::Protocol(_) => close_code::PROTOCOL,
        _ => return None,
    };
    Some((code, error.to_string()))
}

/// One open page: its requests go to its renderer thread, the renderer's messages to the page, and a
/// training run's progress records to the page as they come. The server pings a page a third of the idle
/// time apart and closes it when nothing (not even a pong) came for the idle time.
async fn session(mut page: Page, document: Arc<Document>, live: Option<Arc<Live>>) {
    let mailbox = Arc::new(Mailbox::default());
    let (outbox, mut outgoing) = tokio::sync::mpsc::unbounded_channel();
    let mut progress = live.as_ref().map(|l| l.subscribe());
    let hello = json!({
        "type": "hello",
        "name": document.name,
        "source": document.source,
        "checkpoint": document.trained.is_some(),
        "bake": document.bake().map(|bake| json!({
            "path": document.shown_name(),
            "splats": bake.splats.len(),
            "checkpoint": bake.source.to_string_lossy(),
        })),
        "training": live.as_ref().map(|l| json!({"history": l.history(), "paused": l.paused()})),
    });
    if !page.send_json(&hello).await {
        return;
    }
    if let Some(live) = &live {
        live.listen(&mailbox);
    }
    let worker = {
        let mailbox = Arc::clone(&mailbox);
        let live = live.clone();
        let document = Arc::clone(&document);
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
        page.send_json(&message).await;
        return;
    }
    let mut heard = Instant::now();
    let mut pings = tokio::time::interval(page.idle / 3);
    loop {
        tokio::select! {
            incoming = page.socket.recv() => {
                heard = Instant::now();
                match incoming {
                    Some(Ok(Message::Text(text))) => {
                        if let Err(message) = post(&text, &mailbox, live.as_deref(), &document) {
                            if !page.send_json(&json!({"type": "error", "message": message})).await {
                                break;
                            }
                        }
                    }
                    Some(Ok(Message::Binary(_))) => {
                        page.close(close_code::UNSUPPORTED, "the viewer takes JSON text messages").await;
                        break;
                    }
                    Some(Ok(Message::Close(_))) | None => break,
                    Some(Ok(_)) => {}
                    Some(Err(error)) => {
                        if let Some((code, reason)) = close_for(error) {
                            page.close(code, &reason).await;
                        }
                        break;
                    }
                }
            }
            _ = pings.tick() => {
                if heard.elapsed() >= page.idle {
                    page.close(close_code::POLICY, "nothing heard from the page for the idle time").await;
                    break;
                }
                if !page.send(Message::Ping(Default::default())).await {
                    break;
                }
            }
            Some(record) = next_record(&mut progress) => {
                if !page.send_json(&json!({"type": "progress", "record": record})).await {
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
                if !page.send(message).await {
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
/// run); says what is wrong with a bad one. A bake's script is read-only: the splats do not follow it.
fn post(
    text: &str,
    mailbox: &Mailbox,
    live: Option<&Live>,
    document: &Document,
) -> std::result::Result<(), String> {
    let request: Value =
        serde_json::from_str(text).map_err(|e| format!("a request that is not JSON: {e}"))?;
    let id = request["id"]
        .as_u64()
        .ok_or("a request needs a whole number 'id'")?;
    match request["type"].as_str() {
        Some("source") if live.is_some() => {
            return Err("the script is being trained: edit it once the run has ended".into());
        }
        Some("source") if document.bake().is_some() => {
            return Err(format!(
                "the script is that of the checkpoint the splats were baked from, shown read-only: to edit the \
                 field, view the checkpoint (nerfjit view {})",
                document.bake().map_or_else(Default::default, |b| b.source.to_string_lossy())
            ));
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
