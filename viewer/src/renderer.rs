//! One page's renderer: compiles each script the page sends (answering with diagnostics and, when it
//! compiles, what the scene offers) and renders each camera progressively — a coarse frame at once, finer
//! ones while no newer request waits, the last at full size as PNG. A bake's frames are drawn at full size
//! at once: sent as JPEG, then as PNG once the camera rests.

use std::io::Cursor;
use std::time::{Duration, Instant};

use image::{ImageFormat, RgbImage};
use nerfjit_dsl::diag::line_col;
use nerfjit_dsl::Program;
use serde_json::{json, Value};

use super::export;
use super::live::Live;
use super::mailbox::{ExportRequest, FrameRequest, Mailbox};
use super::scene::Scene;
use super::Document;
use nerfjit::failure::Failure;

/// A message for the page: JSON text, or a frame (a binary message).
#[derive(Debug)]
pub enum Outgoing {
    /// A JSON message.
    Text(String),
    /// A frame or a file: a little-endian u32 header length, the JSON header, then the PNG or JPEG (or
    /// file) bytes.
    Frame(Vec<u8>),
}

/// Where the renderer's messages go; sending fails once the page has gone.
pub type Outbox = tokio::sync::mpsc::UnboundedSender<Outgoing>;

/// Render time per pixel assumed before any frame was timed: so slow that the first frame is the
/// coarsest (a trained hash-grid NeRF takes ~100 µs a pixel, a sphere-traced SDF well under 1 µs).
const FIRST_GUESS_NS_PER_PIXEL: f64 = 1e6;

/// What the first frame after a camera move may take.
const COARSE_FRAME_BUDGET_MS: f64 = 25.0;

/// What a frame may take while a run trains (it is not refined until the run pauses or ends).
const TRAINING_FRAME_BUDGET_MS: f64 = 200.0;

/// The share of the time the viewer renders while a run trains (it rests the remainder).
const TRAINING_SHARE: f64 = 0.05;

/// The longest a refined frame may be expected to take while a run is paused: a larger one would still
/// hold the cores when the run resumes (a frame cannot be stopped midway).
const PAUSED_FRAME_LIMIT_MS: f64 = 500.0;

/// How long the camera must rest before a frame is refined.
const REST: Duration = Duration::from_millis(40);

/// The largest canvas side rendered.
pub const MAX_SIDE: u32 = 4096;

/// Serves `mailbox` until it closes or the page goes: the document's script first, then every request.
/// With a training run, frames show its latest params.
pub fn serve(document: &Document, mailbox: &Mailbox, outbox: &Outbox, live: Option<&Live>) {
    let mut renderer = Renderer {
        document,
        outbox,
        live,
        scene: None,
        source_id: 0,
        params_step: None,
        ns_per_pixel: FIRST_GUESS_NS_PER_PIXEL,
    };
    renderer.compile(&document.source);
    let mut frame: Option<FrameRequest> = None;
    while let Some(pending) = mailbox.take() {
        if let Some((id, text)) = pending.source {
            renderer.source_id = id;
            renderer.compile(&text);
        }
        if pending.refresh {
            renderer.take_new_params();
        }
        if let Some(request) = pending.export {
            if renderer.export(&request).is_err() {
                return;
            }
        }
        frame = pending.frame.or(frame);
        if let Some(request) = &frame {
            if renderer.render(request, mailbox).is_err() {
                return;
            }
        }
    }
}

struct Renderer<'a> {
    document: &'a Document,
    outbox: &'a Outbox,
    live: Option<&'a Live>,
    scene: Option<Scene<'a>>,
    source_id: u64,
    /// The training step of the params shown, with a training run.
    params_step: Option<u32>,
    ns_per_pixel: f64,
}

/// The page has gone.
struct Gone;

impl Renderer<'_> {
    fn send(&self, value: Value) -> Result<(), Gone> {
        self.outbox
            .send(Outgoing::Text(value.to_string()))
            .map_err(|_| Gone)
    }

    fn send_failure(&self, failure: &Failure) -> Result<(), Gone> {
        self.send(json!({"type": "error", "message": failure.to_string().trim()}))
    }

    /// Compiles `text`; sends its diagnostics (none when it compiles) and, when it compiles, the scene.
    /// A script that fails keeps the last scene on screen.
    fn compile(&mut self, text: &str) {
        let start = Instant::now();
        let trained = self.live.and_then(Live::params);
        let compiled = nerfjit_dsl::compile_with(&self.document.name, text, &self.document.overrides)
            .map_err(Failure::Script)
            .and_then(|program| {
                let (params, note) = match &trained {
                    Some((_, params)) => (params.to_vec(), None),
                    None => {
                        let (params, note) = self.document.params_for(&program);
                        (params.to_vec(), note)
                    }
                };
                let script_dir = std::path::Path::new(&self.document.name)
                    .parent()
                    .unwrap_or(std::path::Path::new("."));
                match self.document.bake() {
                    Some(bake) => Scene::of_bake(program, &params, script_dir, bake),
                    None => Scene::compile(program, &params, script_dir),
                }
                .map(|scene| (scene, note))
            });
        self.params_step = trained.map(|(step, _)| step);
        let compile_ms = 1e3 * start.elapsed().as_secs_f64();
        let items = match compiled {
            Ok((scene, note)) => {
                let cameras: Vec<Value> = scene
                    .cameras
                    .iter()
                    .map(|(label, c)| json!({"label": label, "eye": c.eye.to_array(), "target": c.target.to_array(), "up": c.up.to_array(), "focal": c.focal}))
                    .collect();
                let consts: Vec<Value> = scene
                    .consts
                    .iter()
                    .map(|(n, v)| json!({"name": n, "value": v}))
                    .collect();
                let (near, far) = scene.near_far();
                let _ = self.send(json!({
                    "type": "scene",
                    "source_id": self.source_id,
                    "kind": scene.kind(),
                    "layers": scene.layers(),
                    "cameras": cameras,
                    "consts": consts,
                    "near": near,
                    "far": far,
                    "note": note,
                    "compile_ms": compile_ms,
                }));
                self.scene = Some(scene);
                Vec::new()
            }
            Err(failure) => diagnostics(&self.document.name, &failure),
        };
        let _ = self.send(json!({"type": "diagnostics", "source_id": self.source_id, "items": items}));
    }

    /// Makes the file `request` asks for and sends it (or what went wrong).
    fn export(&self, request: &ExportRequest) -> Result<(), Gone> {
        let Some(scene) = &self.scene else {
            return self.send(
                json!({"type": "error", "message": "nothing to export: the script has not compiled yet"}),
            );
        };
        let stem = std::path::Path::new(self.document.shown_name())
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or("scene");
        let step = self.params_step.unwrap_or(0);
        match export::export(request.what, scene, &request.view, stem, step) {
            Ok(file) => {
                let header = json!({"type": "file", "id": request.id, "name": file.name, "mime": file.mime});
                self.outbox
                    .send(Outgoing::Frame(framed(&header, &file.bytes)))
                    .map_err(|_| Gone)
            }
            Err(failure) => self.send_failure(&failure),
        }
    }

    /// Shows the training run's latest params, if newer than those shown.
    fn take_new_params(&mut self) {
        let Some((step, params)) = self.live.and_then(Live::params) else {
            return;
        };
        if let Some(scene) = &mut self.scene {
            if self.params_step != Some(step) {
                scene.set_params(&params);
                self.params_step = Some(step);
            }
        }
    }

    /// Renders `request` at growing sizes until the full one, stopping early when a newer request waits.
    /// While a run trains, renders one small frame and then rests, to leave the cores to training.
    fn render(&mut self, request: &FrameRequest, mailbox: &Mailbox) -> Result<(), Gone> {
        let Some(scene) = &self.scene else {
            return Ok(());
        };
        let training = self.live.is_some_and(Live::busy);
        let (width, height) = (
            request.width.clamp(1, MAX_SIDE),
            request.height.clamp(1, MAX_SIDE),
        );
        if scene.draws_full_frames_at_once() {
            return self.render_at_once(scene, request, mailbox, (width, height));
        }
        let full = f64::from(width) * f64::from(height);
        let budget_ms = if training {
            TRAINING_FRAME_BUDGET_MS
        } else {
            COARSE_FRAME_BUDGET_MS
        };
        let budget_pixels = budget_ms * 1e6 / self.ns_per_pixel;
        let mut divisor = 1u32;
        while f64::from(divisor * divisor) * budget_pixels < full && divisor < 16 {
            divisor *= 2;
        }
        loop {
            let (w, h) = ((width / divisor).max(1), (height / divisor).max(1));
            let start = Instant::now();
            let image = match scene.render(&request.view, w, h, request.layer) {
                Ok(image) => image,
                Err(failure) => return self.send_failure(&failure),
            };
            let seconds = start.elapsed().as_secs_f64();
            self.ns_per_pixel = (1e9 * seconds / (f64::from(w) * f64::from(h))).max(1.0);
            let last = divisor == 1;
            self.send_frame(request, &image, 1e3 * seconds, last)?;
            if training {
                std::thread::sleep(Duration::from_secs_f64(seconds * (1.0 / TRAINING_SHARE - 1.0)));
                return Ok(());
            }
            // A camera being dragged sends a request every few milliseconds: refine only once it rests.
            if last || mailbox.news_within(REST) {
                return Ok(());
            }
            // A paused run may resume at any moment: refine only while the next frame is short, and
            // not at all once it trains again.
            if let Some(live) = self.live.filter(|l| !l.finished()) {
                let next_ms = 4.0 * f64::from(w) * f64::from(h) * self.ns_per_pixel / 1e6;
                if live.busy() || next_ms > PAUSED_FRAME_LIMIT_MS {
                    return Ok(());
                }
            }
            divisor /= 2;
        }
    }

    /// Draws `request` at its full `size` and sends it as JPEG, then the same frame as PNG once the
    /// camera has rested for [`REST`] without a newer request.
    fn render_at_once(
        &self,
        scene: &Scene,
        request: &FrameRequest,
        mailbox: &Mailbox,
        (width, height): (u32, u32),
    ) -> Result<(), Gone> {
        let start = Instant::now();
        let image = match scene.render(&request.view, width, height, request.layer) {
            Ok(image) => image,
            Err(failure) => return self.send_failure(&failure),
        };
        let render_ms = 1e3 * start.elapsed().as_secs_f64();
        self.send_frame(request, &image, render_ms, false)?;
        if mailbox.news_within(REST) {
            return Ok(());
        }
        self.send_frame(request, &image, render_ms, true)
    }

    /// Sends `image`, the frame of `request` that took `render_ms`: the full-size one as PNG (`last`),
    /// others as JPEG. The header says how long the encoding took.
    fn send_frame(
        &self,
        request: &FrameRequest,
        image: &RgbImage,
        render_ms: f64,
        last: bool,
    ) -> Result<(), Gone> {
        let start = Instant::now();
        let encoded = encode(image, last);
        let header = json!({
            "type": "frame",
            "camera_id": request.id,
            "source_id": self.source_id,
            "width": image.width(),
            "height": image.height(),
            "final": last,
            "format": if last { "png" } else { "jpeg" },
            "render_ms": render_ms,
            "encode_ms": 1e3 * start.elapsed().as_secs_f64(),
            "params_step": self.params_step,
        });
        self.outbox
            .send(Outgoing::Frame(framed(&header, &encoded)))
            .map_err(|_| Gone)
    }
}

/// A binary message: the header's length (u32, little-endian), the JSON header, the body.
fn framed(header: &Value, body: &[u8]) -> Vec<u8> {
    let header = header.to_string();
    let mut bytes = (header.len() as u32).to_le_bytes().to_vec();
    bytes.extend_from_slice(header.as_bytes());
    bytes.extend_from_slice(body);
    bytes
}

/// `image` as PNG or as JPEG (quality 85, by `jpeg-encoder`'s vector code).
fn encode(image: &RgbImage, png: bool) -> Vec<u8> {
    if png {
        let mut encoded = Cursor::new(Vec::new());
        image
            .write_to(&mut encoded, ImageFormat::Png)
            .expect("encoding into memory cannot fail");
        return encoded.into_inner();
    }
    let mut encoded = Vec::new();
    // A side is at most MAX_SIDE (4096), within the JPEG limit of 65,535.
    let (width, height) = (image.width() as u16, image.height() as u16);
    jpeg_encoder::Encoder::new(&mut encoded, 85)
        .encode(image.as_raw(), width, height, jpeg_encoder::ColorType::Rgb)
        .expect("encoding into memory cannot fail");
    encoded
}

/// The diagnostics of a failed compile as the page shows them: 1-based line and column of start and end
/// in the page's script (none for a place outside it, such as the prelude), message and hint.
fn diagnostics(name: &str, failure: &Failure) -> Vec<Value> {
    match failure {
        Failure::Script(report) => report
            .diagnostics
            .iter()
            .map(|d| {
                let place = report
                    .sources
                    .file_at(d.span.start as usize)
                    .filter(|f| f.name == name)
                    .map(|f| {
                        let (line, column) = line_col(&f.text, d.span.start as usize - f.base);
                        let (end_line, end_column) = line_col(&f.text, d.span.end as usize - f.base);
                        json!({"line": line, "column": column, "end_line": end_line, "end_column": end_column})
                    });
                json!({"message": d.message, "hint": d.hint, "at": place})
            })
            .collect(),
        other => vec![json!({"message": other.to_string().trim().trim_start_matches("error: "), "hint": null, "at": null})],
    }
}

impl Document {
    /// The params a compiled edit of the document shows: the checkpoint's trained values while the
    /// edit declares the same params, else the script's initial ones (with a note saying so).
    fn params_for<'p>(&'p self, program: &'p Program) -> (&'p [f32], Option<String>) {
        match &self.trained {
            None => (&program.param_values, None),
            Some(trained) if trained.layout == super::param_layout(program) => (&trained.values, None),
            Some(_) => (
                &program.param_values,
                Some("the script's params differ from the checkpoint's: showing their initial values".into()),
            ),
        }
    }
}
