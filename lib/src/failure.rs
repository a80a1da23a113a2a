//! The CLI's error type: script diagnostics (printed with carets) or a plain message.

use std::fmt;

use nerfjit_dsl::{budget, Diagnostic, Program, Report};

/// Why a command failed.
#[derive(Debug)]
pub enum Failure {
    /// Errors in a script, with its sources.
    Script(Report),
    /// Anything else: a missing file, a bad argument, a runtime error.
    Message(String),
    /// Stopped by Ctrl-C or SIGTERM, having saved what it could (said in the message).
    Interrupted(String),
}

impl fmt::Display for Failure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Failure::Script(report) => write!(f, "{report}"),
            Failure::Message(m) => writeln!(f, "error: {m}"),
            Failure::Interrupted(m) => writeln!(f, "interrupted: {m}"),
        }
    }
}

impl std::error::Error for Failure {}

impl From<nerfjit_runtime::Error> for Failure {
    fn from(e: nerfjit_runtime::Error) -> Self {
        Failure::Message(e.to_string())
    }
}

impl From<nerfjit_jit::JitError> for Failure {
    fn from(e: nerfjit_jit::JitError) -> Self {
        Failure::Message(e.to_string())
    }
}

impl From<nerfjit_field::FieldError> for Failure {
    fn from(e: nerfjit_field::FieldError) -> Self {
        match e {
            nerfjit_field::FieldError::Script(report) => Failure::Script(report),
            nerfjit_field::FieldError::Message(m) => Failure::Message(m),
        }
    }
}

impl From<budget::OverBudget> for Failure {
    fn from(e: budget::OverBudget) -> Self {
        Failure::Message(format!("{e}\n  = hint: {}", budget::HINT))
    }
}

impl From<Report> for Failure {
    fn from(r: Report) -> Self {
        Failure::Script(r)
    }
}

/// A diagnostic in `program`'s script as a failure.
pub fn at(program: &Program, d: Diagnostic) -> Failure {
    Failure::Script(Report {
        sources: program.sources.clone(),
        diagnostics: vec![d],
    })
}

/// Shorthand for the CLI's results.
pub type Result<T> = std::result::Result<T, Failure>;
