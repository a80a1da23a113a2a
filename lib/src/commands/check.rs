//! `nerfjit check`: diagnostics, or a summary of the script's functions, params and blocks.

use nerfjit_dsl::config::Settings;
use nerfjit_dsl::Report;

use crate::failure::{Failure, Result};
use crate::script;

/// Checks the script (its blocks' kinds and setting names against the schema, and the setting values
/// that need no files) and describes what it defines.
pub fn run(path: &str) -> Result<String> {
    let program = script::load(path)?;
    let diagnostics: Vec<_> = program
        .blocks()
        .into_iter()
        .flat_map(|b| match Settings::new(&program, b) {
            Ok(settings) => crate::settings::schema::check(&settings)
                .err()
                .unwrap_or_default(),
            Err(d) => vec![d],
        })
        .collect();
    if !diagnostics.is_empty() {
        return Err(Failure::Script(Report {
            sources: program.sources.clone(),
            diagnostics,
        }));
    }
    let mut out = format!("{path}: ok\n");
    for sig in program.functions() {
        out += &format!("  {sig}\n");
    }
    for p in &program.params {
        let n = p.ty.scalars();
        let noun = if n == 1 { "value" } else { "values" };
        out += &format!("  param {}: {} ({n} {noun})\n", p.name, p.ty);
    }
    for b in program.blocks() {
        let name = b
            .name
            .as_ref()
            .map(|n| format!(" {}", n.name))
            .unwrap_or_default();
        out += &format!("  {}{name} {{ {} settings }}\n", b.kind.name, b.entries.len());
    }
    Ok(out)
}
