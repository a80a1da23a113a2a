//! Typed reading of configuration-block values, with errors that point into the script.

use std::path::PathBuf;

use nerfjit_dsl::config::{Spanned, Value};
use nerfjit_dsl::{Diagnostic, Span};

/// The arguments of a call value such as `surround(radius: 3, frames: 20)`, matched to named slots.
pub struct CallArgs {
    name: String,
    span: Span,
    values: Vec<Option<Spanned>>,
    slots: &'static [&'static str],
}

impl CallArgs {
    /// Matches the positional and named arguments of call `v` to `slots`.
    pub fn new(v: &Spanned, slots: &'static [&'static str]) -> Result<CallArgs, Diagnostic> {
        let Value::Call(name, args) = &v.value else {
            return Err(Diagnostic::new(
                v.span,
                format!("expected a call, found {}", v.describe()),
            ));
        };
        let mut values: Vec<Option<Spanned>> = vec![None; slots.len()];
        for (i, (arg_name, value)) in args.iter().enumerate() {
            let slot = match arg_name {
                Some(n) => slots.iter().position(|s| s == n).ok_or_else(|| {
                    Diagnostic::new(value.span, format!("'{name}' has no argument '{n}'"))
                        .with_hint(format!("its arguments are: {}", slots.join(", ")))
                })?,
                None if i < slots.len() => i,
                None => {
                    return Err(
                        Diagnostic::new(value.span, format!("too many arguments for '{name}'"))
                            .with_hint(format!("its arguments are: {}", slots.join(", "))),
                    )
                }
            };
            values[slot] = Some(value.clone());
        }
        Ok(CallArgs {
            name: name.clone(),
            span: v.span,
            values,
            slots,
        })
    }

    /// The span of the whole call.
    pub fn span(&self) -> Span {
        self.span
    }

    /// The value of argument `slot`, if given.
    pub fn raw(&self, slot: &str) -> Option<&Spanned> {
        let i = self.slots.iter().position(|s| *s == slot).expect("known slot");
        self.values[i].as_ref()
    }

    /// Argument `slot` as a number, or `default`.
    pub fn number(&self, slot: &str, default: Option<f64>) -> Result<f64, Diagnostic> {
        match (self.raw(slot), default) {
            (Some(v), _) => v.number(),
            (None, Some(d)) => Ok(d),
            (None, None) => Err(Diagnostic::new(
                self.span,
                format!("'{}' needs the argument '{slot}'", self.name),
            )),
        }
    }

    /// Argument `slot` as a bare name among `choices`, or `default`.
    pub fn choice(&self, slot: &str, choices: &[&str], default: &'static str) -> Result<String, Diagnostic> {
        match self.raw(slot) {
            None => Ok(default.to_string()),
            Some(v) => name_among(v, choices),
        }
    }

    /// Argument `slot` as a string.
    pub fn string(&self, slot: &str) -> Result<String, Diagnostic> {
        match self.raw(slot) {
            Some(v) => v.string().map(str::to_string),
            None => Err(Diagnostic::new(
                self.span,
                format!("'{}' needs the argument '{slot}'", self.name),
            )),
        }
    }
}

/// A bare name among `choices`.
pub fn name_among(v: &Spanned, choices: &[&str]) -> Result<String, Diagnostic> {
    match &v.value {
        Value::Name(n) if choices.contains(&n.as_str()) => Ok(n.clone()),
        _ => Err(Diagnostic::new(
            v.span,
            format!("expected {}, found {}", one_of(&quoted(choices)), v.describe()),
        )),
    }
}

/// A whole number in `lo..=hi`.
pub fn whole(v: &Spanned, lo: u64, hi: u64) -> Result<u64, Diagnostic> {
    let x = v.number()?;
    if x.fract() == 0.0 && x >= lo as f64 && x <= hi as f64 {
        Ok(x as u64)
    } else {
        Err(Diagnostic::new(v.span, format!("{x} is out of range"))
            .with_hint(format!("expected a whole number from {lo} to {hi}")))
    }
}

/// A number in `lo..=hi`.
pub fn ranged(v: &Spanned, lo: f64, hi: f64) -> Result<f64, Diagnostic> {
    let x = v.number()?;
    if x >= lo && x <= hi {
        Ok(x)
    } else {
        Err(
            Diagnostic::new(v.span, format!("{x} is out of range")).with_hint(format!(
                "expected a number from {} to {}",
                short(lo),
                short(hi)
            )),
        )
    }
}

/// Three numbers (a single number is repeated).
pub fn triple(v: &Spanned) -> Result<[f32; 3], Diagnostic> {
    let x = v.numbers(3)?;
    Ok([x[0] as f32, x[1] as f32, x[2] as f32])
}

/// An image size: `N` or `[width, height]`, each side a whole number from 1 to `max`.
pub fn size(v: &Spanned, max: u64) -> Result<(u32, u32), Diagnostic> {
    let side = |x: &Spanned| whole(x, 1, max).map(|n| n as u32);
    match &v.value {
        Value::List(items) if items.len() == 2 => Ok((side(&items[0])?, side(&items[1])?)),
        _ => side(v).map(|n| (n, n)),
    }
}

/// An output file's name ending in one of `formats` (any when empty); `none` (no file) when `may_be_none`.
pub fn output_name(v: &Spanned, formats: &[&str], may_be_none: bool) -> Result<Option<PathBuf>, Diagnostic> {
    if may_be_none && matches!(&v.value, Value::Name(n) if n == "none") {
        return Ok(None);
    }
    let path = PathBuf::from(v.string()?);
    let extension = path.extension().and_then(|e| e.to_str()).unwrap_or("");
    if !formats.is_empty() && !formats.contains(&extension) {
        let listed: Vec<String> = formats.iter().map(|f| format!(".{f}")).collect();
        return Err(Diagnostic::new(
            v.span,
            format!("cannot write '{}': unknown format", path.display()),
        )
        .with_hint(format!("use a file ending in {}", one_of(&listed))));
    }
    Ok(Some(path))
}

/// `x` as a person writes it: `0.5`, `100`, `1e-12`, `1e6`.
pub fn short(x: f64) -> String {
    if x != 0.0 && !(1e-3..1e5).contains(&x.abs()) {
        format!("{x:e}")
    } else {
        x.to_string()
    }
}

/// `items` as a person lists alternatives: `a`, `a or b`, `a, b or c`.
pub fn one_of(items: &[String]) -> String {
    match items {
        [] => String::new(),
        [one] => one.clone(),
        [rest @ .., last] => format!("{} or {last}", rest.join(", ")),
    }
}

/// Each of `names` in quotes.
fn quoted(names: &[&str]) -> Vec<String> {
    names.iter().map(|n| format!("'{n}'")).collect()
}
