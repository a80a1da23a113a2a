//! Lexer: source text to tokens with spans. Comments are `//` to the end of the line.

use crate::diag::{Diagnostic, Span};

/// The kinds of token of the language.
#[derive(Clone, Debug, PartialEq)]
pub enum Tok {
    /// A name: letters, digits and `_`, not starting with a digit.
    Ident(String),
    /// A numeric literal such as `1`, `0.25` or `1e-5`.
    Number(f64),
    /// A string literal in double quotes.
    Str(String),
    /// Punctuation or an operator, e.g. `(`, `->`, `..`, `<=`.
    Punct(&'static str),
    /// End of input.
    Eof,
}

/// A token and where it stands.
#[derive(Clone, Debug, PartialEq)]
pub struct Token {
    /// What the token is.
    pub tok: Tok,
    /// Where it is.
    pub span: Span,
}

const PUNCTS: [&str; 26] = [
    "->", "..", "<=", ">=", "==", "!=", "&&", "||", "(", ")", "{", "}", "[", "]", ",", ":", ";", "=", "+",
    "-", "*", "/", "<", ">", ".", "!",
];

/// Splits `source` into tokens, ending with [`Tok::Eof`].
pub fn lex(source: &str) -> Result<Vec<Token>, Diagnostic> {
    let bytes = source.as_bytes();
    let mut tokens = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i];
        if c.is_ascii_whitespace() {
            i += 1;
        } else if source[i..].starts_with("//") {
            i += source[i..].find('\n').unwrap_or(source.len() - i);
        } else if c.is_ascii_alphabetic() || c == b'_' {
            let start = i;
            while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || bytes[i] == b'_') {
                i += 1;
            }
            tokens.push(token(Tok::Ident(source[start..i].to_string()), start, i));
        } else if c.is_ascii_digit() || (c == b'.' && bytes.get(i + 1).is_some_and(u8::is_ascii_digit)) {
            let start = i;
            i = number_end(bytes, i);
            while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || bytes[i] == b'_') {
                i += 1;
            }
            let text = &source[start..i];
            let value: f64 = text.parse().map_err(|_| {
                Diagnostic::new(Span::new(start, i), format!("malformed number '{text}'"))
                    .with_hint("numbers look like 1, 0.25, 1e-5 or 2.5e3")
            })?;
            if value > f64::from(f32::MAX) {
                return Err(Diagnostic::new(
                    Span::new(start, i),
                    format!("the number '{text}' does not fit in a 32-bit float"),
                )
                .with_hint(format!("numbers are at most {:e}", f32::MAX)));
            }
            tokens.push(token(Tok::Number(value), start, i));
        } else if c == b'"' {
            let start = i;
            let rest = &source[i + 1..];
            match rest.find(['"', '\n']) {
                Some(end) if rest.as_bytes()[end] == b'"' => {
                    tokens.push(token(Tok::Str(rest[..end].to_string()), start, i + end + 2));
                    i += end + 2;
                }
                _ => {
                    return Err(
                        Diagnostic::new(Span::new(start, start + 1), "unterminated string")
                            .with_hint("close the string with '\"' on the same line"),
                    );
                }
            }
        } else if let Some(p) = PUNCTS.iter().find(|p| source[i..].starts_with(**p)) {
            tokens.push(token(Tok::Punct(p), i, i + p.len()));
            i += p.len();
        } else {
            let ch = source[i..].chars().next().unwrap_or('?');
            return Err(Diagnostic::new(
                Span::new(i, i + ch.len_utf8()),
                format!("unexpected character '{}'", ch.escape_default()),
            ));
        }
    }
    tokens.push(token(Tok::Eof, source.len(), source.len()));
    Ok(tokens)
}

fn token(tok: Tok, start: usize, end: usize) -> Token {
    Token {
        tok,
        span: Span::new(start, end),
    }
}

/// The end of the number starting at `i`: digits, an optional fraction (not `..`), an optional exponent.
fn number_end(bytes: &[u8], mut i: usize) -> usize {
    let digits = |mut i: usize| {
        while i < bytes.len() && bytes[i].is_ascii_digit() {
            i += 1;
        }
        i
    };
    i = digits(i);
    if bytes.get(i) == Some(&b'.') && bytes.get(i + 1) != Some(&b'.') {
        i = digits(i + 1);
    }
    if matches!(bytes.get(i), Some(b'e' | b'E')) {
        let mut j = i + 1;
        if matches!(bytes.get(j), Some(b'+' | b'-')) {
            j += 1;
        }
        if bytes.get(j).is_some_and(u8::is_ascii_digit) {
            i = digits(j);
        }
    }
    i
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kinds(s: &str) -> Vec<Tok> {
        lex(s).unwrap().into_iter().map(|t| t.tok).collect()
    }

    #[test]
    fn numbers_beyond_f32_are_errors_at_their_place() {
        for text in ["1e39", "1e999", "340282350000000000000000000000000000001"] {
            let source = format!("x = {text} + 1");
            let e = lex(&source).unwrap_err();
            assert!(
                e.message.contains("does not fit in a 32-bit float"),
                "{}",
                e.message
            );
            assert_eq!((e.span.start as usize, e.span.end as usize), (4, 4 + text.len()));
        }
        assert_eq!(kinds("3.4e38"), vec![Tok::Number(3.4e38), Tok::Eof]);
    }

    #[test]
    fn numbers_with_exponents_and_ranges() {
        assert_eq!(
            kinds("1e-5 2.5E3 .5 3..4"),
            vec![
                Tok::Number(1e-5),
                Tok::Number(2500.0),
                Tok::Number(0.5),
                Tok::Number(3.0),
                Tok::Punct(".."),
                Tok::Number(4.0),
                Tok::Eof
            ]
        );
    }

    #[test]
    fn comments_and_strings() {
        assert_eq!(
            kinds("a // c\n\"x.gif\" ->"),
            vec![
                Tok::Ident("a".into()),
                Tok::Str("x.gif".into()),
                Tok::Punct("->"),
                Tok::Eof
            ]
        );
        assert!(lex("\"open").is_err());
        assert!(lex("a # b").is_err());
    }
}
