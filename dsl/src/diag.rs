//! Diagnostics: errors with a source span, rendered as `file:line:col`, the source line and a caret.

use std::fmt;

/// A half-open byte range `start..end` into a source text.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Span {
    /// First byte of the span.
    pub start: u32,
    /// One past the last byte of the span.
    pub end: u32,
}

impl Span {
    /// No place in the sources: for mistakes about the script as a whole, such as a function that a command
    /// names and the script lacks.
    pub const NOWHERE: Span = Span {
        start: u32::MAX,
        end: u32::MAX,
    };

    /// The span `start..end`.
    pub fn new(start: usize, end: usize) -> Span {
        Span {
            start: start as u32,
            end: end.max(start) as u32,
        }
    }

    /// The smallest span covering both `self` and `other`.
    pub fn to(self, other: Span) -> Span {
        Span {
            start: self.start.min(other.start),
            end: self.end.max(other.end),
        }
    }
}

/// One error found in a script, pointing at the source.
#[derive(Clone, Debug, PartialEq)]
pub struct Diagnostic {
    /// What is wrong, in one line.
    pub message: String,
    /// Where it is wrong.
    pub span: Span,
    /// How it might be fixed, when that is known.
    pub hint: Option<String>,
}

impl Diagnostic {
    /// An error at `span` without a hint.
    pub fn new(span: Span, message: impl Into<String>) -> Diagnostic {
        Diagnostic {
            message: message.into(),
            span,
            hint: None,
        }
    }

    /// The same error with a hint attached.
    pub fn with_hint(mut self, hint: impl Into<String>) -> Diagnostic {
        self.hint = Some(hint.into());
        self
    }
}

/// The 1-based line and column (in characters) of byte offset `offset` in `source`.
pub fn line_col(source: &str, offset: usize) -> (usize, usize) {
    let offset = floor_char_boundary(source, offset.min(source.len()));
    let before = &source[..offset];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    let col = source[line_start..offset].chars().count() + 1;
    (line, col)
}

fn floor_char_boundary(s: &str, mut i: usize) -> usize {
    while i > 0 && !s.is_char_boundary(i) {
        i -= 1;
    }
    i
}

/// One source file and the offset at which its spans start.
#[derive(Clone, Debug)]
pub struct SourceFile {
    /// The name shown in diagnostics.
    pub name: String,
    /// The span offset of its first byte.
    pub base: usize,
    /// The text.
    pub text: String,
}

/// The sources of a program (the prelude and the script), laid end to end in one span space.
#[derive(Clone, Debug, Default)]
pub struct SourceMap {
    /// The files, by increasing `base`.
    pub files: Vec<SourceFile>,
}

impl SourceMap {
    /// Adds a file after the existing ones and returns its base offset.
    pub fn add(&mut self, name: &str, text: &str) -> usize {
        let base = self.files.last().map_or(0, |f| f.base + f.text.len() + 1);
        self.files.push(SourceFile {
            name: name.to_string(),
            base,
            text: text.to_string(),
        });
        base
    }

    /// The file that holds offset `at`.
    pub fn file_at(&self, at: usize) -> Option<&SourceFile> {
        self.files.iter().rev().find(|f| f.base <= at)
    }
}

/// A set of diagnostics together with the sources they refer to, ready to print.
#[derive(Clone, Debug)]
pub struct Report {
    /// The sources the spans index into.
    pub sources: SourceMap,
    /// The errors, in source order.
    pub diagnostics: Vec<Diagnostic>,
}

/// Most diagnostics a report shows; the rest are counted.
const MAX_SHOWN_DIAGNOSTICS: usize = 20;

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, d) in self.diagnostics.iter().take(MAX_SHOWN_DIAGNOSTICS).enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            match self.sources.file_at(d.span.start as usize) {
                Some(file) if d.span != Span::NOWHERE => {
                    let local = Span::new(d.span.start as usize - file.base, d.span.end as usize - file.base);
                    render(f, &file.name, &file.text, local, d)?;
                }
                _ => {
                    writeln!(f, "error: {}", abbreviated(&d.message))?;
                    if let Some(hint) = &d.hint {
                        writeln!(f, "  = hint: {}", abbreviated(hint))?;
                    }
                }
            }
        }
        let hidden = self.diagnostics.len().saturating_sub(MAX_SHOWN_DIAGNOSTICS);
        if hidden > 0 {
            writeln!(f, "\n... and {hidden} more errors")?;
        }
        Ok(())
    }
}

impl std::error::Error for Report {}

/// Writes one diagnostic as
/// ```text
/// error: unknown function 'lenght'
///  --> scene.sdf:4:17
///   |
/// 4 |     let d = lenght(p) - 1.0
///   |             ^^^^^^
///   = hint: did you mean 'length'?
/// ```
fn render(f: &mut fmt::Formatter<'_>, file: &str, source: &str, span: Span, d: &Diagnostic) -> fmt::Result {
    let start = (span.start as usize).min(source.len());
    let (line, col) = line_col(source, start);
    writeln!(f, "error: {}", abbreviated(&d.message))?;
    let gutter = line.to_string().len();
    writeln!(f, "{:gutter$}--> {file}:{line}:{col}", "")?;
    let text = source.lines().nth(line - 1).unwrap_or("");
    let text = text.trim_end_matches('\r');
    writeln!(f, "{:gutter$} |", "")?;
    let span_chars = {
        let end = floor_char_boundary(source, (span.end as usize).min(source.len()));
        let begin = floor_char_boundary(source, start);
        let line_end = begin + source[begin..].find('\n').unwrap_or(source.len() - begin);
        source[begin..end.min(line_end)].chars().count().max(1)
    };
    let shown = Excerpt::of(text, col - 1, span_chars);
    writeln!(f, "{line} | {}", shown.text)?;
    let pad: String = shown
        .text
        .chars()
        .take(shown.caret_at)
        .map(|c| if c == '\t' { '\t' } else { ' ' })
        .collect();
    writeln!(f, "{:gutter$} | {pad}{}", "", "^".repeat(shown.carets))?;
    if let Some(hint) = &d.hint {
        writeln!(f, "{:gutter$} = hint: {}", "", abbreviated(hint))?;
    }
    Ok(())
}

/// Most characters of a source line shown in a diagnostic; longer lines are cut around the span.
const MAX_SHOWN_CHARS: usize = 120;

/// Most characters of a message or hint shown; longer ones (quoting a huge name from the script) lose
/// their middle.
const MAX_MESSAGE_CHARS: usize = 400;

/// `text`, or its first and last characters around a `…` if it is longer than `MAX_MESSAGE_CHARS`.
fn abbreviated(text: &str) -> String {
    let count = text.chars().count();
    if count <= MAX_MESSAGE_CHARS {
        return text.to_string();
    }
    let head: String = text.chars().take(MAX_MESSAGE_CHARS - 100).collect();
    let tail: String = text.chars().skip(count - 100).collect();
    format!("{head} … {tail}")
}

/// The part of a source line a diagnostic shows, and where its caret goes.
struct Excerpt {
    /// The line, or a window of it with `…` where it was cut.
    text: String,
    /// Characters of `text` before the first caret.
    caret_at: usize,
    /// Carets to draw.
    carets: usize,
}

impl Excerpt {
    /// The excerpt of `line` for a span of `span_chars` characters from character `col` (0-based).
    fn of(line: &str, col: usize, span_chars: usize) -> Excerpt {
        let chars: Vec<char> = line.chars().collect();
        if chars.len() <= MAX_SHOWN_CHARS {
            return Excerpt {
                text: line.to_string(),
                caret_at: col,
                carets: span_chars,
            };
        }
        let col = col.min(chars.len());
        let first = col
            .saturating_sub(MAX_SHOWN_CHARS / 3)
            .min(chars.len() - MAX_SHOWN_CHARS);
        let last = first + MAX_SHOWN_CHARS;
        let (before, after) = (
            if first > 0 { "…" } else { "" },
            if last < chars.len() { "…" } else { "" },
        );
        let window: String = chars[first..last].iter().collect();
        Excerpt {
            text: format!("{before}{window}{after}"),
            caret_at: col - first + before.chars().count(),
            carets: span_chars.min(last - col).max(1),
        }
    }
}

/// Edit distance counting insertions, deletions, substitutions and swaps of neighbours (optimal string
/// alignment), for "did you mean" hints.
pub fn edit_distance(a: &str, b: &str) -> usize {
    let (a, b): (Vec<char>, Vec<char>) = (a.chars().collect(), b.chars().collect());
    let mut d = vec![vec![0usize; b.len() + 1]; a.len() + 1];
    for (i, row) in d.iter_mut().enumerate() {
        row[0] = i;
    }
    for (j, cell) in d[0].iter_mut().enumerate() {
        *cell = j;
    }
    for i in 1..=a.len() {
        for j in 1..=b.len() {
            let cost = usize::from(a[i - 1] != b[j - 1]);
            d[i][j] = (d[i - 1][j] + 1).min(d[i][j - 1] + 1).min(d[i - 1][j - 1] + cost);
            if i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1] {
                d[i][j] = d[i][j].min(d[i - 2][j - 2] + 1);
            }
        }
    }
    d[a.len()][b.len()]
}

/// Names longer than this get no "did you mean" (whose cost grows with the product of the lengths).
const MAX_SUGGESTED_CHARS: usize = 64;

/// The candidate closest to `name`, if it is close enough to be a likely typo.
pub fn closest<'a>(name: &str, candidates: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    let length = name.chars().count();
    if length > MAX_SUGGESTED_CHARS {
        return None;
    }
    let limit = (length / 3).max(1);
    candidates
        .into_iter()
        .filter(|c| c.chars().count().abs_diff(length) <= limit)
        .map(|c| (edit_distance(name, c), c))
        .filter(|&(d, _)| d <= limit)
        .min()
        .map(|(_, c)| c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_line_column_and_caret() {
        let source = "fn sdf(p: vec3) -> f32 {\n    lenght(p) - 1.0\n}\n";
        let mut sources = SourceMap::default();
        sources.add("prelude.sdf", "fn x() -> f32 = 1\n");
        let base = sources.add("scene.sdf", source);
        let report = Report {
            sources,
            diagnostics: vec![
                Diagnostic::new(Span::new(base + 29, base + 35), "unknown function 'lenght'")
                    .with_hint("did you mean 'length'?"),
            ],
        };
        let text = report.to_string();
        assert_eq!(
            text,
            "error: unknown function 'lenght'\n --> scene.sdf:2:5\n  |\n2 |     lenght(p) - 1.0\n  |     ^^^^^^\n  = hint: did you mean 'length'?\n"
        );
    }

    #[test]
    fn long_lines_are_cut_around_the_span() {
        let line = format!("{}lenght(p){}", "a + ".repeat(100), " + b".repeat(100));
        let source = format!("fn f() -> f32 = 1\n{line}\n");
        let mut sources = SourceMap::default();
        let base = sources.add("long.sdf", &source);
        let at = base + 18 + 400;
        let report = Report {
            sources,
            diagnostics: vec![Diagnostic::new(
                Span::new(at, at + 6),
                "unknown function 'lenght'",
            )],
        };
        let text = report.to_string();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[1], " --> long.sdf:2:401");
        let shown = lines[3].strip_prefix("2 | ").unwrap();
        assert!(shown.starts_with('…') && shown.ends_with('…'), "{shown}");
        assert_eq!(shown.chars().count(), MAX_SHOWN_CHARS + 2);
        let caret = lines[4].strip_prefix("  | ").unwrap();
        let under: String = shown.chars().skip(caret.find('^').unwrap()).take(6).collect();
        assert_eq!(under, "lenght");
        assert_eq!(caret.trim(), "^^^^^^");
        // A message quoting a huge name loses its middle.
        let long = format!("unknown function '{}'", "x".repeat(10_000));
        let shown = abbreviated(&long);
        assert_eq!(shown.chars().count(), MAX_MESSAGE_CHARS + 3);
        assert!(shown.starts_with("unknown function 'xxx") && shown.ends_with("xxx'"));
        assert_eq!(abbreviated("short"), "short");
        // A span at the very end of a long line stays in the window.
        assert_eq!(Excerpt::of(&"x".repeat(1000), 999, 5).carets, 1);
        assert!(Excerpt::of(&"x".repeat(1000), 999, 5).text.starts_with('…'));
    }

    #[test]
    fn closest_finds_typos_only() {
        assert_eq!(closest("lenght", ["length", "dot", "cross"]), Some("length"));
        assert_eq!(closest("banana", ["length", "dot"]), None);
        let long = "x".repeat(100_000);
        assert_eq!(closest(&long, [long.as_str()]), None);
    }
}
