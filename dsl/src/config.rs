//! Configuration blocks (`render ... { }`, `train { }`): their values, evaluated, with spans for errors.

use crate::ast::{ConfigBlock, Expr, ExprKind};
use crate::diag::{closest, Diagnostic, Span};
use crate::program::Program;

/// A configuration value.
#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    /// A number (constant expressions are evaluated).
    Number(f64),
    /// A string.
    Str(String),
    /// A bare name such as `z` or `lambert`.
    Name(String),
    /// A call such as `surround(radius: 3, frames: 20)`.
    Call(String, Vec<(Option<String>, Spanned)>),
    /// A list of values, e.g. `[0, 0, 0]`.
    List(Vec<Spanned>),
}

/// A value with the span it was written at.
#[derive(Clone, Debug, PartialEq)]
pub struct Spanned {
    /// The value.
    pub value: Value,
    /// Where it was written.
    pub span: Span,
}

impl Spanned {
    /// The value as a number.
    pub fn number(&self) -> Result<f64, Diagnostic> {
        match &self.value {
            Value::Number(x) => Ok(*x),
            _ => Err(Diagnostic::new(
                self.span,
                format!("expected a number, found {}", self.describe()),
            )),
        }
    }

    /// The value as a string.
    pub fn string(&self) -> Result<&str, Diagnostic> {
        match &self.value {
            Value::Str(s) => Ok(s),
            _ => Err(
                Diagnostic::new(self.span, format!("expected a string, found {}", self.describe()))
                    .with_hint("write it in double quotes, e.g. \"out/torus.gif\""),
            ),
        }
    }

    /// The value as a list of n numbers (a single number is repeated).
    pub fn numbers(&self, n: usize) -> Result<Vec<f64>, Diagnostic> {
        match &self.value {
            Value::Number(x) => Ok(vec![*x; n]),
            Value::List(items) if items.len() == n => items.iter().map(Spanned::number).collect(),
            _ => Err(Diagnostic::new(
                self.span,
                format!("expected {n} numbers, found {}", self.describe()),
            )
            .with_hint(format!("write a list such as [{}]", vec!["0"; n].join(", ")))),
        }
    }

    /// A short description for error messages.
    pub fn describe(&self) -> String {
        match &self.value {
            Value::Number(x) => format!("number {x}"),
            Value::Str(s) => format!("string \"{s}\""),
            Value::Name(n) => format!("name '{n}'"),
            Value::Call(n, _) => format!("call '{n}(...)'"),
            Value::List(items) => format!("a list of {}", items.len()),
        }
    }
}

/// The entries of one block, evaluated; [`Settings::take`] each known key, then [`Settings::finish`]
/// reports any key left over as unknown.
#[derive(Clone, Debug)]
pub struct Settings {
    /// The block's kind and optional name.
    pub kind: String,
    /// The block's name, if any (`sphere_trace` in `render sphere_trace { }`).
    pub name: Option<String>,
    /// The whole block's span.
    pub span: Span,
    entries: Vec<(String, Span, Spanned)>,
}

impl Settings {
    /// Evaluates the entries of `block`.
    pub fn new(program: &Program, block: &ConfigBlock) -> Result<Settings, Diagnostic> {
        let mut entries: Vec<(String, Span, Spanned)> = Vec::new();
        for e in &block.entries {
            if entries.iter().any(|(k, _, _)| *k == e.key.name) {
                return Err(Diagnostic::new(
                    e.key.span,
                    format!("setting '{}' is given twice", e.key.name),
                ));
            }
            entries.push((e.key.name.clone(), e.key.span, value(program, &e.value)?));
        }
        Ok(Settings {
            kind: block.kind.name.clone(),
            name: block.name.as_ref().map(|n| n.name.clone()),
            span: block.span,
            entries,
        })
    }

    /// The span of the value of setting `key`, if present.
    pub fn span_of(&self, key: &str) -> Option<Span> {
        self.entries
            .iter()
            .find(|(k, _, _)| k == key)
            .map(|(_, _, v)| v.span)
    }

    /// Removes and returns setting `key`, if present.
    pub fn take(&mut self, key: &str) -> Option<Spanned> {
        let i = self.entries.iter().position(|(k, _, _)| k == key)?;
        Some(self.entries.remove(i).2)
    }

    /// Fails on the first setting not taken yet, suggesting the closest of `known`.
    pub fn finish(&self, known: &[&str]) -> Result<(), Diagnostic> {
        match self.entries.first() {
            None => Ok(()),
            Some((key, span, _)) => {
                let block = match &self.name {
                    Some(name) => format!("{} {name}", self.kind),
                    None => self.kind.clone(),
                };
                let mut d = Diagnostic::new(*span, format!("unknown setting '{key}' in '{block}' block"));
                d = match closest(key, known.iter().copied()) {
                    Some(c) => d.with_hint(format!("did you mean '{c}'?")),
                    None => d.with_hint(format!("known settings: {}", known.join(", "))),
                };
                Err(d)
            }
        }
    }
}

fn value(program: &Program, e: &Expr) -> Result<Spanned, Diagnostic> {
    let v = match &e.kind {
        ExprKind::Str(s) => Value::Str(s.clone()),
        ExprKind::Var(name) if program.eval_constant(e).is_err() => Value::Name(name.clone()),
        ExprKind::Call(name, args) => Value::Call(
            name.name.clone(),
            args.iter()
                .map(|a| Ok((a.name.as_ref().map(|n| n.name.clone()), value(program, &a.value)?)))
                .collect::<Result<_, Diagnostic>>()?,
        ),
        ExprKind::List(items) | ExprKind::Tuple(items) if program.eval_constant(e).is_err() => Value::List(
            items
                .iter()
                .map(|i| value(program, i))
                .collect::<Result<_, _>>()?,
        ),
        _ => {
            let values = program.eval_constant(e)?;
            if values.len() == 1 && !matches!(e.kind, ExprKind::List(_)) {
                Value::Number(values[0])
            } else {
                Value::List(
                    values
                        .into_iter()
                        .map(|x| Spanned {
                            value: Value::Number(x),
                            span: e.span,
                        })
                        .collect(),
                )
            }
        }
    };
    Ok(Spanned {
        value: v,
        span: e.span,
    })
}
