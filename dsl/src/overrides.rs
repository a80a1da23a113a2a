//! `--set` overrides: replace a `const`'s value or a block setting before a script is checked.

use crate::ast::{ConfigBlock, ConfigEntry, Ident, Item, Script};
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

/// The block `selector` names: `kind` or `name` (`render`, `sphere_trace`, `train`, `sdf`) for the first
/// block of that kind or name, `kind[i]` or `name[i]` for the i-th (from 0).
fn select_block<'s>(
    script: &'s mut Script,
    selector: &str,
    span: Span,
) -> Result<&'s mut ConfigBlock, Diagnostic> {
    let (name, index) = match selector.strip_suffix(']').and_then(|s| s.split_once('[')) {
        Some((name, i)) => {
            let index = i.trim().parse::<usize>().map_err(|_| {
                Diagnostic::new(
                    span,
                    format!("'{selector}': the index in [ ] must be a whole number from 0"),
                )
            })?;
            (name.trim(), index)
        }
        None => (selector, 0),
    };
    let describe = |b: &ConfigBlock| match &b.name {
        Some(n) => format!("{} {}", b.kind.name, n.name),
        None => b.kind.name.clone(),
    };
    let all: Vec<String> = script
        .items
        .iter()
        .filter_map(|i| match i {
            Item::Block(b) => Some(describe(b)),
            _ => None,
        })
        .collect();
    let mut chosen: Vec<&'s mut ConfigBlock> = script
        .items
        .iter_mut()
        .filter_map(|i| match i {
            Item::Block(b) if b.kind.name == name || b.name.as_ref().is_some_and(|n| n.name == name) => {
                Some(b)
            }
            _ => None,
        })
        .collect();
    let count = chosen.len();
    if index < count {
        return Ok(chosen.swap_remove(index));
    }
    let blocks = if all.is_empty() {
        "the script has no blocks".to_string()
    } else {
        format!("its blocks are: {}", all.join(", "))
    };
    let message = match count {
        0 => format!("the script has no '{name}' block"),
        1 => format!("the script has one '{name}' block: {name} or {name}[0]"),
        n => format!(
            "the script has {n} '{name}' blocks: {name}[0] to {name}[{}]",
            n - 1
        ),
    };
    Err(Diagnostic::new(span, message).with_hint(format!(
        "{blocks}; address a block by kind or name, e.g. render.size=64, render[1].size=64 or sphere_trace.size=64"
    )))
}

fn set_setting(
    script: &mut Script,
    selector: &str,
    key: &str,
    span: Span,
    value: crate::ast::Expr,
) -> Result<(), Diagnostic> {
    let block = select_block(script, selector, span)?;
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

#[cfg(test)]
mod tests {
    use crate::compile_with;
    use crate::config::Settings;

    const SCRIPT: &str = "fn sdf(p: vec3) -> f32 = length(p) - 1\n\
        render sphere_trace { size: 16 }\n\
        render volume { size: 8 }\n\
        render sphere_trace { size: 4 }\n";

    /// The `size` of each block after `overrides`.
    fn sizes(overrides: &[&str]) -> Vec<f64> {
        let overrides: Vec<String> = overrides.iter().map(|s| s.to_string()).collect();
        let program = compile_with("s.sdf", SCRIPT, &overrides).unwrap();
        program
            .blocks()
            .into_iter()
            .map(|b| {
                Settings::new(&program, b)
                    .unwrap()
                    .take("size")
                    .unwrap()
                    .number()
                    .unwrap()
            })
            .collect()
    }

    #[test]
    fn a_setting_is_set_in_the_block_its_kind_name_or_index_selects() {
        assert_eq!(sizes(&["render.size=1"]), [1.0, 8.0, 4.0]);
        assert_eq!(sizes(&["render[1].size=1"]), [16.0, 1.0, 4.0]);
        assert_eq!(sizes(&["render[2].size=1"]), [16.0, 8.0, 1.0]);
        assert_eq!(sizes(&["sphere_trace[1].size=1"]), [16.0, 8.0, 1.0]);
        assert_eq!(sizes(&["volume.size=1", "sphere_trace.size=2"]), [2.0, 1.0, 4.0]);
    }

    #[test]
    fn a_selector_beyond_the_blocks_says_which_there_are() {
        let error = |o: &str| {
            compile_with("s.sdf", SCRIPT, &[o.to_string()])
                .unwrap_err()
                .to_string()
        };
        let text = error("render[3].size=1");
        assert!(
            text.contains("the script has 3 'render' blocks: render[0] to render[2]"),
            "{text}"
        );
        assert!(
            text.contains("its blocks are: render sphere_trace, render volume, render sphere_trace"),
            "{text}"
        );
        assert!(error("volume[1].size=1").contains("one 'volume' block: volume or volume[0]"));
        assert!(error("train.steps=1").contains("the script has no 'train' block"));
        assert!(error("render[x].size=1").contains("must be a whole number"));
    }
}
