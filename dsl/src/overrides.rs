//! `--set` overrides: replace a `const`'s value or a block setting before a script is checked.

use crate::ast::{ConfigEntry, Ident, Item, Script};
use crate::diag::{closest, Diagnostic, Span};
use crate::parser::parse;

/// Applies one override `target=value` (whose text starts at span offset `at`) to `script`.
pub fn apply(script: &mut Script, text: &str, at: usize) -> Result<(), Diagnostic> {
    let Some(eq) = text.find('=') else {
        return Err(Diagnostic::new(
            Span::new(at, at + text.len()),
            format!("'{text}' is not name=value"),
        )
        .with_hint("write e.g. --set beta=0.1 or --set train.steps=100"));
    };
    let target = text[..eq].trim();
    let target_span = Span::new(at, at + eq);
    let value = value_expr(&text[eq + 1..], at + eq + 1)?;
    match target.split_once('.') {
        None => set_const(script, target, target_span, value),
        Some((kind, key)) => set_setting(script, kind, key, target_span, value),
    }
}

/// Parses the value as an expression (by parsing `const _ = value`).
fn value_expr(text: &str, at: usize) -> Result<crate::ast::Expr, Diagnostic> {
    let shift = "const _ = ".len();
    let parsed = parse(&format!("const _ = {text}"), at - shift)?;
    match &parsed.items[..] {
        [Item::Const(c)] => Ok(c.value.clone()),
        _ => Err(
            Diagnostic::new(Span::new(at, at + text.len()), "expected one value")
                .with_hint("write a number, a vector like [1, 2, 3], a string in quotes, or a call"),
        ),
    }
}

fn set_const(script: &mut Script, name: &str, span: Span, value: crate::ast::Expr) -> Result<(), Diagnostic> {
    let names: Vec<String> = script
        .items
        .iter()
        .filter_map(|i| match i {
            Item::Const(c) => Some(c.name.name.clone()),
            _ => None,
        })
        .collect();
    for item in &mut script.items {
        if let Item::Const(c) = item {
            if c.name.name == name {
                c.value = value;
                return Ok(());
            }
        }
    }
    let mut d = Diagnostic::new(span, format!("the script has no const '{name}' to set"));
    d = match closest(name, names.iter().map(String::as_str)) {
        Some(c) => d.with_hint(format!("did you mean '{c}'?")),
        None => d.with_hint(
            "declare it in the script with 'const NAME = value', or set a block setting as kind.key",
        ),
    };
    Err(d)
}

fn set_setting(
    script: &mut Script,
    kind: &str,
    key: &str,
    span: Span,
    value: crate::ast::Expr,
) -> Result<(), Diagnostic> {
    let block = script.items.iter_mut().find_map(|i| match i {
        Item::Block(b) if b.kind.name == kind => Some(b),
        _ => None,
    });
    let Some(block) = block else {
        return Err(Diagnostic::new(span, format!("the script has no '{kind}' block")));
    };
    match block.entries.iter_mut().find(|e| e.key.name == key) {
        Some(entry) => entry.value = value,
        None => block.entries.push(ConfigEntry {
            key: Ident {
                name: key.to_string(),
                span,
            },
            value,
        }),
    }
    Ok(())
}
