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

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, d) in self.diagnostics.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            match self.sources.file_at(d.span.start as usize) {
                _ if d.span == Span::NOWHERE => {
                    writeln!(f, "error: {}", d.message)?;
                    if let Some(hint) = &d.hint {
                        writeln!(f, "  = hint: {hint}")?;
                    }
                }
                Some(file) => {
                    let local = Span::new(d.span.start as usize - file.base, d.span.end as usize - file.base);
                    render(f, &file.name, &file.text, local, d)?;
                }
                None => writeln!(f, "error: {}", d.message)?,
            }
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
    writeln!(f, "error: {}", d.message)?;
    let gutter = line.to_string().len();
    writeln!(f, "{:gutter$}--> {file}:{line}:{col}", "")?;
    let text = source.lines().nth(line - 1).unwrap_or("");
    let text = text.trim_end_matches('\r');
    writeln!(f, "{:gutter$} |", "")?;
    writeln!(f, "{line} | {text}")?;
    let span_chars = {
        let end = floor_char_boundary(source, (span.end as usize).min(source.len()));
        let begin = floor_char_boundary(source, start);
        let line_end = begin + source[begin..].find('\n').unwrap_or(source.len() - begin);
        source[begin..end.min(line_end)].chars().count().max(1)
    };
    let pad: String = text
        .chars()
        .take(col - 1)
        .map(|c| if c == '\t' { '\t' } else { ' ' })
        .collect();
    writeln!(f, "{:gutter$} | {pad}{}", "", "^".repeat(span_chars))?;
    if let Some(hint) = &d.hint {
        writeln!(f, "{:gutter$} = hint: {hint}", "")?;
    }
    Ok(())
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

/// The candidate closest to `name`, if it is close enough to be a likely typo.
pub fn closest<'a>(name: &str, candidates: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    let limit = (name.chars().count() / 3).max(1);
    candidates
        .into_iter()
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
    fn closest_finds_typos_only() {
        assert_eq!(closest("lenght", ["length", "dot", "cross"]), Some("length"));
        assert_eq!(closest("banana", ["length", "dot"]), None);
    }
}
