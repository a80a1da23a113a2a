//! Loading scripts: from a file, or one of the examples embedded in the binary by `build.rs`.

use std::path::Path;

use nerfjit_dsl::MAX_SOURCE_BYTES;
use nerfjit_dsl::{compile_with, Program};
use nerfjit_runtime::input::read_text_at_most;

use crate::failure::{Failure, Result};

include!(concat!(env!("OUT_DIR"), "/examples.rs"));

/// Reads and checks the script at `path`. A path that does not exist but names an embedded example
/// (`torus`, `torus.sdf` or `examples/torus.sdf`) loads that example.
pub fn load(path: &str) -> Result<Program> {
    load_with(path, &[])
}

/// [`load`] with `--set` overrides (`name=value` for a const, `kind.key=value` for a block setting).
pub fn load_with(path: &str, overrides: &[String]) -> Result<Program> {
    let (name, source) = read(path)?;
    compile_with(&name, &source, overrides).map_err(Failure::Script)
}

/// The name and source text of the script at `path` (or of the embedded example it names), unchecked.
pub fn read(path: &str) -> Result<(String, String)> {
    // At most one byte more than a script may hold is read, so a stream such as /dev/zero is refused.
    match read_text_at_most(Path::new(path), MAX_SOURCE_BYTES as u64) {
        Ok(source) => Ok((path.to_string(), source)),
        Err(e) => {
            let file = Path::new(path)
                .file_name()
                .and_then(|f| f.to_str())
                .unwrap_or(path);
            let wanted = if file.ends_with(".sdf") {
                file.to_string()
            } else {
                format!("{file}.sdf")
            };
            match EXAMPLES.iter().find(|(n, _)| *n == wanted) {
                Some((n, source)) if !Path::new(path).exists() => {
                    Ok((format!("examples/{n}"), source.to_string()))
                }
                _ => Err(Failure::Message(format!("cannot read script '{path}': {e}"))),
            }
        }
    }
}

/// The list of embedded examples, or the source of one.
pub fn examples(name: Option<&str>) -> Result<String> {
    match name {
        None => Ok(EXAMPLES.iter().map(|(n, _)| format!("{n}\n")).collect()),
        Some(name) => read(name).map(|(_, source)| source),
    }
}
