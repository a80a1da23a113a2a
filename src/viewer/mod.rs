//! `nerfjit view`: a live view of a script or a checkpoint in the browser. The page orbits the scene,
//! edits the script (re-checked, re-compiled and re-rendered on every edit, diagnostics at their line and
//! column) and moves its consts with sliders.
//!
//! The page runs native code compiled from what is typed into it, so the server binds the loopback address
//! unless told otherwise and answers nothing without the random token in the URL it prints.

mod mailbox;
mod renderer;
mod scene;
mod server;

use std::net::{IpAddr, SocketAddr};

use nerfjit_dsl::{Program, Type};

use crate::failure::{Failure, Result};

/// What `nerfjit view` serves and where.
pub struct ViewArgs<'a> {
    /// A script, or a checkpoint written by a train block.
    pub source: &'a str,
    /// The address to bind.
    pub host: IpAddr,
    /// The port (0: any free one).
    pub port: u16,
}

/// The script a page starts from and, for a checkpoint, its trained params.
pub struct Document {
    /// The script's name in diagnostics.
    pub name: String,
    /// Its text.
    pub source: String,
    /// A checkpoint's params.
    trained: Option<Trained>,
}

/// A checkpoint's trained params.
struct Trained {
    /// The names and types of the params, in order.
    layout: Vec<(String, Type)>,
    /// Their values.
    values: Vec<f32>,
}

impl Document {
    /// The document of a script file (or shipped example) or a checkpoint.
    pub fn load(source: &str) -> Result<Document> {
        let (program, params) = crate::views::load(source)?;
        let file = program
            .sources
            .files
            .last()
            .ok_or_else(|| Failure::Message(format!("{source} holds no script")))?;
        let is_checkpoint = crate::views::is_checkpoint(source);
        Ok(Document {
            name: file.name.clone(),
            source: file.text.clone(),
            trained: is_checkpoint.then(|| Trained {
                layout: param_layout(&program),
                values: params,
            }),
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

/// Serves the page until the process is stopped; prints its URL (with the token) first.
pub fn run(args: &ViewArgs) -> Result<()> {
    let document = Document::load(args.source)?;
    let token = new_token()?;
    let address = SocketAddr::new(args.host, args.port);
    let listener = std::net::TcpListener::bind(address)
        .map_err(|e| Failure::Message(format!("cannot listen on {address}: {e}")))?;
    let bound = listener
        .local_addr()
        .map_err(|e| Failure::Message(format!("cannot read the listening address: {e}")))?;
    if !args.host.is_loopback() {
        eprintln!(
            "warning: serving on {bound}: anyone who can reach it and has the token runs code on this machine"
        );
    }
    crate::emit(&format!(
        "nerfjit view: {} on http://{bound}/?token={token}\n",
        document.name
    ));
    server::serve(listener, document, token)
}
