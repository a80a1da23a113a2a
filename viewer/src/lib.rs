//! `nerfjit view`: a live view of a script or a checkpoint in the browser. The page orbits the scene,
//! edits the script (re-checked, re-compiled and re-rendered on every edit, diagnostics at their line and
//! column) and moves its consts with sliders. A bake is orbited as its splats, with the script of the
//! checkpoint it was baked from shown read-only. `nerfjit run --view` follows a training run through [`Live`],
//! the library's [`nerfjit::observe::TrainingObserver`].
//!
//! The page runs native code compiled from what is typed into it, so the server binds the loopback address
//! unless told otherwise and answers nothing without the random token in the URL it prints.

mod export;
mod live;
mod mailbox;
mod renderer;
mod scene;
mod server;

use std::net::{IpAddr, SocketAddr, TcpListener};
use std::path::Path;
use std::sync::Arc;

pub use live::Live;
pub use server::Limits;

use nerfjit_dsl::{Program, Type};

use nerfjit::bake_file::Bake;
use nerfjit::failure::{Failure, Result};

/// What `nerfjit view` serves and where.
pub struct ViewArgs<'a> {
    /// A script, a checkpoint written by a train block, or a bake (`.bake`) of one.
    pub source: &'a str,
    /// The address to bind.
    pub host: IpAddr,
    /// The port (0: any free one).
    pub port: u16,
    /// What the server gives its clients.
    pub limits: Limits,
}

/// The script a page starts from and, for a checkpoint, its trained params; for a bake, the splats too.
pub struct Document {
    /// The script's name in diagnostics.
    pub name: String,
    /// Its text.
    pub source: String,
    /// `--set` overrides every compile of it applies.
    overrides: Vec<String>,
    /// A checkpoint's params.
    trained: Option<Trained>,
    /// The bake shown instead of the field, with the path it was read from.
    baked: Option<(String, Bake)>,
}

/// A checkpoint's trained params.
struct Trained {
    /// The names and types of the params, in order.
    layout: Vec<(String, Type)>,
    /// Their values.
    values: Vec<f32>,
}

impl Document {
    /// The document of a script file (or shipped example), a checkpoint, or a bake (its splats, with the
    /// script and params of the checkpoint it was baked from).
    pub fn load(source: &str) -> Result<Document> {
        if !nerfjit::bake_file::is_bake(Path::new(source)) {
            let (program, params) = nerfjit::checkpoint::load_source(source)?;
            return Document::of(&program, params, nerfjit::checkpoint::is_checkpoint(source));
        }
        let bake = nerfjit::bake_file::read(Path::new(source))?;
        let checkpoint = bake.source.to_string_lossy().into_owned();
        let (program, params) = nerfjit::checkpoint::load_source(&checkpoint).map_err(|failure| {
            Failure::Message(format!(
                "'{source}' was baked from '{checkpoint}', whose script and cameras the viewer shows (it must \
                 stay where it was when baked): {}",
                failure.to_string().trim().trim_start_matches("error: ")
            ))
        })?;
        let mut document = Document::of(&program, params, true)?;
        document.baked = Some((source.to_string(), bake));
        Ok(document)
    }

    /// The bake shown, if the document is one.
    pub fn bake(&self) -> Option<&Bake> {
        self.baked.as_ref().map(|(_, bake)| bake)
    }

    /// The name the page and the commands it shows use: the bake's path for a bake, else the script's.
    pub fn shown_name(&self) -> &str {
        self.baked.as_ref().map_or(&self.name, |(path, _)| path)
    }

    /// The document of `program` (its script and `--set` overrides) with `params`, trained ones for a
    /// checkpoint.
    pub fn of(program: &Program, params: Vec<f32>, is_checkpoint: bool) -> Result<Document> {
        let files = &program.sources.files;
        let overrides = files
            .iter()
            .filter(|f| f.name == "--set")
            .map(|f| f.text.clone())
            .collect();
        let file = files
            .iter()
            .rev()
            .find(|f| f.name != "<prelude>" && f.name != "--set")
            .ok_or_else(|| Failure::Message("the program holds no script".into()))?;
        Ok(Document {
            name: file.name.clone(),
            source: file.text.clone(),
            overrides,
            trained: is_checkpoint.then(|| Trained {
                layout: param_layout(program),
                values: params,
            }),
            baked: None,
        })
    }
}

/// The names and types of `program`'s params, in order.
fn param_layout(program: &Program) -> Vec<(String, Type)> {
    program
        .params
        .iter()
        .map(|p| (p.name.clone(), p.ty.clone()))
        .collect()
}

/// A random access token: 128 bits as hex.
fn new_token() -> Result<String> {
    let mut bytes = [0u8; 16];
    getrandom::fill(&mut bytes)
        .map_err(|e| Failure::Message(format!("cannot draw a random access token: {e}")))?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// Binds the address and prints the page's URL with a new token.
fn open(args: &ViewArgs, document: &Document) -> Result<(TcpListener, String)> {
    let token = new_token()?;
    let address = SocketAddr::new(args.host, args.port);
    let listener = TcpListener::bind(address)
        .map_err(|e| Failure::Message(format!("cannot listen on {address}: {e}")))?;
    let bound = listener
        .local_addr()
        .map_err(|e| Failure::Message(format!("cannot read the listening address: {e}")))?;
    if !args.host.is_loopback() {
        eprintln!(
            "warning: serving on {bound}: anyone who can reach it and has the token runs code on this machine"
        );
    }
    let shown = match document.bake() {
        Some(bake) => format!(
            "{} ({} splats baked from {})",
            document.shown_name(),
            bake.splats.len(),
            bake.source.display()
        ),
        None => document.name.clone(),
    };
    nerfjit::emit(&format!(
        "nerfjit view: {shown} on http://{bound}/?token={token}\n"
    ));
    Ok((listener, token))
}

/// `nerfjit view`: serves the page until the process is stopped; prints its URL (with the token) first.
pub fn run(args: &ViewArgs) -> Result<()> {
    let document = Document::load(args.source)?;
    let (listener, token) = open(args, &document)?;
    server::serve(listener, document, token, None, args.limits)
}

/// `nerfjit run --view`: serves the page of a training run from a thread of its own, for as long as the
/// process lives; prints its URL first.
pub fn attach(args: &ViewArgs, document: Document, live: Arc<Live>) -> Result<()> {
    let (listener, token) = open(args, &document)?;
    let limits = args.limits;
    std::thread::Builder::new()
        .name("nerfjit view server".into())
        .spawn(move || {
            if let Err(failure) = server::serve(listener, document, token, Some(live), limits) {
                eprint!("{failure}");
            }
        })
        .map_err(|e| Failure::Message(format!("cannot start the viewer: {e}")))?;
    Ok(())
}
