//! Recursive-descent parser: tokens to a [`Script`]. Nesting depth and program size are limited so that
//! no input can overflow the stack.

use crate::ast::*;
use crate::diag::{Diagnostic, Span};
use crate::ir::GridSpec;
use crate::lexer::{lex, Tok, Token};
use crate::types::Type;

/// Deepest nesting of expressions (parentheses, calls, blocks, unary operators) the parser accepts.
pub const MAX_DEPTH: usize = 200;
/// Longest path from an expression to its deepest part the parser accepts, counting each link of an
/// operator chain (`a + b + c` is two deep) or of a swizzle and index chain (`v.xy[0]`), and each level
/// of nesting. The later passes recurse along such paths: at most 2·`MAX_HEIGHT` frames deep, a few
/// kilobytes each, so the `nerfjit` binary runs them on a thread with a large stack.
pub const MAX_HEIGHT: usize = 10_000;
/// Largest script the parser accepts, in bytes.
pub const MAX_SOURCE_BYTES: usize = 4 << 20;
/// Largest vector or matrix dimension a type may name.
pub const MAX_DIM: usize = 1 << 16;
/// Most floats a grid encoding's table may hold (2^28 floats: 1 GiB).
pub const MAX_GRID_PARAMS: u64 = 1 << 28;

/// Parses a whole script whose spans start at byte offset `base` (see [`crate::diag::SourceMap`]).
pub fn parse(source: &str, base: usize) -> Result<Script, Diagnostic> {
    if source.len() > MAX_SOURCE_BYTES {
        return Err(Diagnostic::new(
            Span::new(base, base),
            format!(
                "script is too large ({} bytes; the limit is {MAX_SOURCE_BYTES})",
                source.len()
            ),
        ));
    }
    let shift = |s: Span| Span::new(s.start as usize + base, s.end as usize + base);
    let mut tokens = lex(source).map_err(|mut d| {
        d.span = shift(d.span);
        d
    })?;
    for t in &mut tokens {
        t.span = shift(t.span);
    }
    let mut p = Parser {
        tokens,
        pos: 0,
        depth: 0,
        height: 0,
    };
    let mut script = Script::default();
    while p.peek() != &Tok::Eof {
        script.items.push(p.item()?);
    }
    Ok(script)
}

struct Parser {
    tokens: Vec<Token>,
    pos: usize,
    depth: usize,
    /// Nesting levels plus the chain links open above the current position (see [`MAX_HEIGHT`]).
    height: usize,
}

type PResult<T> = Result<T, Diagnostic>;

impl Parser {
    fn peek(&self) -> &Tok {
        &self.tokens[self.pos].tok
    }

    fn peek_at(&self, ahead: usize) -> &Tok {
        &self.tokens[(self.pos + ahead).min(self.tokens.len() - 1)].tok
    }

    fn span(&self) -> Span {
        self.tokens[self.pos].span
    }

    fn prev_span(&self) -> Span {
        self.tokens[self.pos.saturating_sub(1)].span
    }

    fn bump(&mut self) -> Token {
        let t = self.tokens[self.pos].clone();
        if self.pos + 1 < self.tokens.len() {
            self.pos += 1;
        }
        t
    }

    fn is(&self, punct: &str) -> bool {
        matches!(self.peek(), Tok::Punct(p) if *p == punct)
    }

    fn eat(&mut self, punct: &str) -> bool {
        let found = self.is(punct);
        if found {
            self.bump();
        }
        found
    }

    fn is_keyword(&self, word: &str) -> bool {
        matches!(self.peek(), Tok::Ident(w) if w == word)
    }

    fn describe(tok: &Tok) -> String {
        match tok {
            Tok::Ident(s) => format!("'{s}'"),
            Tok::Number(n) => format!("number {n}"),
            Tok::Str(s) => format!("string \"{s}\""),
            Tok::Punct(p) => format!("'{p}'"),
            Tok::Eof => "end of file".into(),
        }
    }

    fn expect(&mut self, punct: &str) -> PResult<Span> {
        if self.is(punct) {
            return Ok(self.bump().span);
        }
        let found = Self::describe(self.peek());
        let err = Diagnostic::new(self.span(), format!("expected '{punct}', found {found}"));
        Err(match punct {
            ")" | "]" | "}" => err.with_hint(format!("is a '{punct}' missing?")),
            _ => err,
        })
    }

    fn ident(&mut self, what: &str) -> PResult<Ident> {
        match self.peek().clone() {
            Tok::Ident(name) => {
                let span = self.bump().span;
                Ok(Ident { name, span })
            }
            other => Err(Diagnostic::new(
                self.span(),
                format!("expected {what}, found {}", Self::describe(&other)),
            )),
        }
    }

    fn enter(&mut self) -> PResult<()> {
        self.depth += 1;
        if self.depth > MAX_DEPTH {
            return Err(Diagnostic::new(self.span(), "expression nested too deeply")
                .with_hint(format!("the limit is {MAX_DEPTH} levels; split it with 'let'")));
        }
        self.link()
    }

    /// Leaves a level entered by [`Parser::enter`].
    fn leave(&mut self) {
        self.depth -= 1;
        self.height -= 1;
    }

    /// One more link of an operator, swizzle or index chain.
    fn link(&mut self) -> PResult<()> {
        self.height += 1;
        if self.height > MAX_HEIGHT {
            return Err(Diagnostic::new(self.span(), "expression too long")
                .with_hint(format!(
                    "at most {MAX_HEIGHT} chained operations and nesting levels in one expression; split it with 'let'"
                )));
        }
        Ok(())
    }

    fn item(&mut self) -> PResult<Item> {
        let Tok::Ident(word) = self.peek().clone() else {
            return Err(Diagnostic::new(
                self.span(),
                format!("expected an item, found {}", Self::describe(self.peek())),
            )
            .with_hint("a script holds 'fn', 'param', 'const' and blocks such as 'render { ... }'"));
        };
        match word.as_str() {
            "fn" => self.fn_def().map(Item::Fn),
            "param" => {
                self.bump();
                let name = self.ident("a param name")?;
                self.expect(":")?;
                let ty = self.type_expr()?;
                self.expect("=")?;
                let init = self.expr()?;
                self.eat(";");
                Ok(Item::Param(ParamDecl { name, ty, init }))
            }
            "const" => {
                self.bump();
                let name = self.ident("a constant name")?;
                self.expect("=")?;
                let value = self.expr()?;
                self.eat(";");
                Ok(Item::Const(ConstDecl { name, value }))
            }
            _ => self.config_block().map(Item::Block),
        }
    }

    fn fn_def(&mut self) -> PResult<FnDef> {
        self.bump();
        let name = self.ident("a function name")?;
        self.expect("(")?;
        let mut params = Vec::new();
        while !self.is(")") {
            let pname = self.ident("a parameter name")?;
            self.expect(":")?;
            let ty = self.type_expr()?;
            let default = if self.eat("=") { Some(self.expr()?) } else { None };
            params.push(FnParam {
                name: pname,
                ty,
                default,
            });
            if !self.eat(",") {
                break;
            }
        }
        self.expect(")")?;
        if !self.is("->") {
            return Err(Diagnostic::new(self.span(), "expected '->' and the result type")
                .with_hint("write e.g. 'fn sdf(p: vec3) -> f32 { ... }'"));
        }
        self.bump();
        let ret = self.type_expr()?;
        let body = if self.eat("=") {
            let e = self.expr()?;
            self.eat(";");
            e
        } else if self.is("{") {
            self.block()?
        } else {
            return Err(Diagnostic::new(
                self.span(),
                format!("expected '{{' or '=' for the body of '{}'", name.name),
            ));
        };
        Ok(FnDef {
            name,
            params,
            ret,
            body,
        })
    }

    fn dim(&mut self) -> PResult<usize> {
        let span = self.span();
        match self.bump().tok {
            Tok::Number(n) if n >= 1.0 && n.fract() == 0.0 && n <= MAX_DIM as f64 => Ok(n as usize),
            _ => Err(Diagnostic::new(span, "expected a dimension (a whole number ≥ 1)")
                .with_hint(format!("dimensions range from 1 to {MAX_DIM}"))),
        }
    }

    /// `<input, width, depth>` or `<input, width, depth, skip: k>` after `mlp`.
    fn mlp_shape(&mut self) -> PResult<Type> {
        let start = self.span();
        self.expect("<")?;
        let input = self.dim()?;
        self.expect(",")?;
        let width = self.dim()?;
        self.expect(",")?;
        let depth = self.dim()?;
        let mut skip = None;
        if self.eat(",") {
            let key = self.ident("'skip'")?;
            if key.name != "skip" {
                return Err(
                    Diagnostic::new(key.span, format!("unknown mlp option '{}'", key.name))
                        .with_hint("write mlp<39, 128, 6, skip: 3>"),
                );
            }
            self.expect(":")?;
            let at = self.span();
            let k = self.dim()?;
            if k >= depth {
                return Err(Diagnostic::new(
                    at,
                    format!("the skip layer must be one of the layers 1..{depth}"),
                )
                .with_hint("layers count from 0; layer 0 already reads the input"));
            }
            skip = Some(k);
        }
        self.expect(">")?;
        let shape = crate::types::MlpShape {
            input,
            width,
            depth,
            skip,
        };
        if Type::Mlp(shape.clone()).scalars() > MAX_DIM * MAX_DIM {
            return Err(Diagnostic::new(
                start.to(self.prev_span()),
                "this network has too many weights",
            ));
        }
        Ok(Type::Mlp(shape))
    }

    /// `<3, key: value, ...>` after `hashgrid` (`hashed`) or `grid`: the settings of a grid encoding, each
    /// checked against its range, and the table's size against [`MAX_GRID_PARAMS`].
    fn grid_shape(&mut self, hashed: bool) -> PResult<Type> {
        let start = self.span();
        let kind = if hashed { "hashgrid" } else { "grid" };
        let example = if hashed {
            "write hashgrid<3, levels: 16, features: 2, log2_size: 19, base: 16, finest: 2048, bounds: 1.5>"
        } else {
            "write grid<3, res: 128, features: 4, bounds: 1.5>"
        };
        self.expect("<")?;
        let at = self.span();
        if self.dim()? != 3 {
            return Err(Diagnostic::new(at, format!("a {kind} is 3-dimensional")).with_hint(example));
        }
        let keys: &[(&str, f64, f64)] = if hashed {
            &[
                ("levels", 1.0, 32.0),
                ("features", 1.0, 64.0),
                ("log2_size", 4.0, 26.0),
                ("base", 1.0, 65536.0),
                ("finest", 1.0, 1048576.0),
                ("bounds", 0.0, 1e6),
            ]
        } else {
            &[
                ("res", 2.0, 4096.0),
                ("features", 1.0, 64.0),
                ("bounds", 0.0, 1e6),
            ]
        };
        let mut values: Vec<Option<f64>> = vec![None; keys.len()];
        while self.eat(",") {
            let key = self.ident("a setting")?;
            let Some(k) = keys.iter().position(|(name, ..)| *name == key.name) else {
                let names = keys.iter().map(|(n, ..)| *n);
                let mut d = Diagnostic::new(key.span, format!("unknown {kind} setting '{}'", key.name));
                d = match crate::diag::closest(&key.name, names.clone()) {
                    Some(c) => d.with_hint(format!("did you mean '{c}'?")),
                    None => d.with_hint(format!(
                        "{kind} settings are: {}",
                        names.collect::<Vec<_>>().join(", ")
                    )),
                };
                return Err(d);
            };
            self.expect(":")?;
            let span = self.span();
            let (name, lo, hi) = keys[k];
            let value = match self.bump().tok {
                Tok::Number(n) if name == "bounds" && n > lo && n <= hi => n,
                Tok::Number(n) if n.fract() == 0.0 && (lo..=hi).contains(&n) => n,
                _ if name == "bounds" => {
                    return Err(Diagnostic::new(
                        span,
                        "bounds is the half extent of the grid's cube, a number > 0",
                    )
                    .with_hint("bounds: 1.5 covers [-1.5, 1.5]³"))
                }
                _ => {
                    return Err(Diagnostic::new(
                        span,
                        format!("{kind} setting '{name}' is a whole number from {lo} to {hi}"),
                    )
                    .with_hint(example))
                }
            };
            values[k] = Some(value);
        }
        self.expect(">")?;
        let span = start.to(self.prev_span());
        let get = |name: &str, default: f64| {
            let k = keys.iter().position(|(n, ..)| *n == name).expect("a known key");
            values[k].unwrap_or(default)
        };
        let extent = (get("bounds", 1.5) as f32).to_bits();
        let layout = if hashed {
            let (base, finest) = (get("base", 16.0) as u32, get("finest", 2048.0) as u32);
            if finest < base {
                return Err(
                    Diagnostic::new(span, format!("finest ({finest}) is below base ({base})"))
                        .with_hint("the levels grow from base to finest cells per axis"),
                );
            }
            GridSpec {
                table: 0,
                levels: get("levels", 16.0) as u32,
                features: get("features", 2.0) as u32,
                log2_size: get("log2_size", 19.0) as u32,
                base,
                finest,
                extent,
            }
        } else {
            let Some(res) = values[0] else {
                return Err(Diagnostic::new(span, "a grid needs its resolution").with_hint(example));
            };
            let cells = res as u32 - 1;
            let vertices = u64::from(cells + 1).pow(3);
            GridSpec {
                table: 0,
                levels: 1,
                features: get("features", 1.0) as u32,
                // A table as large as the vertices: never hashed.
                log2_size: 64 - (vertices - 1).leading_zeros(),
                base: cells,
                finest: cells,
                extent,
            }
        };
        let floats = layout.n_params();
        if floats > MAX_GRID_PARAMS {
            return Err(Diagnostic::new(
                span,
                format!(
                    "this {kind} needs {floats} floats ({:.1} GiB); the limit is {MAX_GRID_PARAMS} floats (1 GiB)",
                    floats as f64 * 4.0 / f64::from(1u32 << 30)
                ),
            )
            .with_hint("use fewer levels or features, or a smaller log2_size or res"));
        }
        Ok(Type::Grid(crate::types::GridShape { hashed, layout }))
    }

    fn type_expr(&mut self) -> PResult<TypeExpr> {
        let start = self.span();
        if self.eat("(") {
            let mut types = Vec::new();
            while !self.is(")") {
                types.push(self.type_expr()?.ty);
                if !self.eat(",") {
                    break;
                }
            }
            self.expect(")")?;
            return Ok(TypeExpr {
                ty: Type::Tuple(types),
                span: start.to(self.prev_span()),
            });
        }
        let name = self.ident("a type")?;
        let ty = match name.name.as_str() {
            "f32" => Type::F32,
            "vec2" => Type::Vec(2),
            "vec3" => Type::Vec(3),
            "vec4" => Type::Vec(4),
            "vec" => {
                self.expect("<")?;
                let n = self.dim()?;
                self.expect(">")?;
                Type::Vec(n)
            }
            "mat" => {
                self.expect("<")?;
                let r = self.dim()?;
                self.expect(",")?;
                let c = self.dim()?;
                self.expect(">")?;
                Type::Mat(r, c)
            }
            "mlp" => self.mlp_shape()?,
            "hashgrid" => self.grid_shape(true)?,
            "grid" => self.grid_shape(false)?,
            other => {
                let mut d = Diagnostic::new(name.span, format!("unknown type '{other}'"));
                let names = [
                    "f32", "vec2", "vec3", "vec4", "vec", "mat", "mlp", "hashgrid", "grid",
                ];
                if matches!(other, "float" | "double" | "f64" | "real" | "scalar") {
                    d = d.with_hint("did you mean 'f32'?");
                } else if let Some(c) = crate::diag::closest(other, names) {
                    d = d.with_hint(format!("did you mean '{c}'?"));
                } else {
                    d = d.with_hint(
                        "types are f32, vec2, vec3, vec4, vec<N>, mat<R, C>, mlp<I, W, D>, hashgrid<3, ...> and grid<3, ...>",
                    );
                }
                return Err(d);
            }
        };
        Ok(TypeExpr {
            ty,
            span: start.to(self.prev_span()),
        })
    }

    fn config_block(&mut self) -> PResult<ConfigBlock> {
        let kind = self.ident("a block kind")?;
        let name = if matches!(self.peek(), Tok::Ident(_)) {
            Some(self.ident("a block name")?)
        } else {
            None
        };
        if !self.is("{") {
            return Err(Diagnostic::new(
                kind.span,
                format!("unknown item '{}'", kind.name),
            )
            .with_hint("items start with 'fn', 'param', 'const', or are blocks like 'render sphere_trace { ... }'"));
        }
        self.bump();
        let mut entries = Vec::new();
        while !self.is("}") {
            let key = self.ident("a setting name")?;
            self.expect(":")?;
            let value = self.expr()?;
            entries.push(ConfigEntry { key, value });
            if !self.eat(",") && !self.eat(";") {
                break;
            }
        }
        self.expect("}")?;
        let span = kind.span.to(self.prev_span());
        Ok(ConfigBlock {
            kind,
            name,
            entries,
            span,
        })
    }

    fn block(&mut self) -> PResult<Expr> {
        self.enter()?;
        let start = self.expect("{")?;
        let mut lets = Vec::new();
        while self.is_keyword("let") {
            self.bump();
            let pattern = if self.eat("(") {
                let mut names = Vec::new();
                while !self.is(")") {
                    names.push(self.ident("a name")?);
                    if !self.eat(",") {
                        break;
                    }
                }
                self.expect(")")?;
                Pattern::Tuple(names)
            } else {
                Pattern::Name(self.ident("a name after 'let'")?)
            };
            self.expect("=")?;
            let value = self.expr()?;
            self.eat(";");
            lets.push(Let { pattern, value });
        }
        if self.is("}") {
            return Err(
                Diagnostic::new(self.span(), "a block must end with an expression")
                    .with_hint("the last line of a block is its value, e.g. 'length(q) - 0.25'"),
            );
        }
        let value = self.expr()?;
        self.eat(";");
        let end = self.expect("}")?;
        self.leave();
        Ok(Expr {
            kind: ExprKind::Block(lets, Box::new(value)),
            span: start.to(end),
        })
    }

    /// Parses an expression (lowest precedence: `||`).
    pub fn expr(&mut self) -> PResult<Expr> {
        self.enter()?;
        let e = self.binary(0)?;
        self.leave();
        Ok(e)
    }

    fn binary(&mut self, level: usize) -> PResult<Expr> {
        const LEVELS: [&[(&str, BinOp)]; 5] = [
            &[("||", BinOp::Or)],
            &[("&&", BinOp::And)],
            &[
                ("<=", BinOp::Le),
                (">=", BinOp::Ge),
                ("==", BinOp::Eq),
                ("!=", BinOp::Ne),
                ("<", BinOp::Lt),
                (">", BinOp::Gt),
            ],
            &[("+", BinOp::Add), ("-", BinOp::Sub)],
            &[("*", BinOp::Mul), ("/", BinOp::Div)],
        ];
        if level == LEVELS.len() {
            return self.unary();
        }
        let mut lhs = self.binary(level + 1)?;
        let mut links = 0;
        while let Some(&(_, op)) = LEVELS[level].iter().find(|(s, _)| self.is(s)) {
            self.link()?;
            links += 1;
            self.bump();
            let rhs = self.binary(level + 1)?;
            let span = lhs.span.to(rhs.span);
            lhs = Expr {
                kind: ExprKind::Binary(op, Box::new(lhs), Box::new(rhs)),
                span,
            };
        }
        self.height -= links;
        Ok(lhs)
    }

    fn unary(&mut self) -> PResult<Expr> {
        let start = self.span();
        let op = if self.eat("-") {
            UnOp::Neg
        } else if self.eat("!") {
            UnOp::Not
        } else {
            return self.postfix();
        };
        self.enter()?;
        let operand = self.unary()?;
        self.leave();
        let span = start.to(operand.span);
        Ok(Expr {
            kind: ExprKind::Unary(op, Box::new(operand)),
            span,
        })
    }

    fn postfix(&mut self) -> PResult<Expr> {
        let mut e = self.primary()?;
        let mut links = 0;
        loop {
            if self.is(".") || self.is("[") {
                self.link()?;
                links += 1;
            }
            if self.eat(".") {
                let field = self.ident("a swizzle such as 'xy' after '.'")?;
                let span = e.span.to(field.span);
                e = Expr {
                    kind: ExprKind::Swizzle(Box::new(e), field),
                    span,
                };
            } else if self.eat("[") {
                let first = self.expr()?;
                let end = if self.eat("..") { Some(self.expr()?) } else { None };
                let close = self.expect("]")?;
                let span = e.span.to(close);
                let kind = match end {
                    Some(end) => ExprKind::Slice(Box::new(e), Box::new(first), Box::new(end)),
                    None => ExprKind::Index(Box::new(e), Box::new(first)),
                };
                e = Expr { kind, span };
            } else {
                self.height -= links;
                return Ok(e);
            }
        }
    }

    fn list(&mut self, close: &str) -> PResult<Vec<Expr>> {
        let mut items = Vec::new();
        while !self.is(close) {
            items.push(self.expr()?);
            if !self.eat(",") {
                break;
            }
        }
        self.expect(close)?;
        Ok(items)
    }

    fn primary(&mut self) -> PResult<Expr> {
        let start = self.span();
        let kind = match self.peek().clone() {
            Tok::Number(n) => {
                self.bump();
                ExprKind::Number(n)
            }
            Tok::Str(s) => {
                self.bump();
                ExprKind::Str(s)
            }
            Tok::Ident(word) if word == "if" => return self.if_expr(),
            Tok::Ident(_) => {
                let name = self.ident("a name")?;
                if self.eat("(") {
                    let mut args = Vec::new();
                    while !self.is(")") {
                        let arg_name = match (self.peek(), self.peek_at(1)) {
                            (Tok::Ident(_), Tok::Punct(":")) => {
                                let n = self.ident("an argument name")?;
                                self.bump();
                                Some(n)
                            }
                            _ => None,
                        };
                        let value = self.expr()?;
                        args.push(Arg {
                            name: arg_name,
                            value,
                        });
                        if !self.eat(",") {
                            break;
                        }
                    }
                    self.expect(")")?;
                    ExprKind::Call(name, args)
                } else {
                    ExprKind::Var(name.name)
                }
            }
            Tok::Punct("(") => {
                self.bump();
                let mut items = self.list(")")?;
                if items.len() == 1 {
                    let mut inner = items.pop().expect("one item");
                    inner.span = start.to(self.prev_span());
                    return Ok(inner);
                }
                ExprKind::Tuple(items)
            }
            Tok::Punct("[") => {
                self.bump();
                ExprKind::List(self.list("]")?)
            }
            Tok::Punct("{") => return self.block(),
            other => {
                return Err(Diagnostic::new(
                    start,
                    format!("expected an expression, found {}", Self::describe(&other)),
                ))
            }
        };
        Ok(Expr {
            kind,
            span: start.to(self.prev_span()),
        })
    }

    fn if_expr(&mut self) -> PResult<Expr> {
        self.enter()?;
        let start = self.bump().span;
        let cond = self.expr_no_block()?;
        let then = self.block()?;
        if !self.is_keyword("else") {
            return Err(Diagnostic::new(self.span(), "'if' needs an 'else' branch")
                .with_hint("both branches give a value: 'if c { a } else { b }'"));
        }
        self.bump();
        let other = if self.is_keyword("if") {
            self.if_expr()?
        } else {
            self.block()?
        };
        let span = start.to(other.span);
        self.leave();
        Ok(Expr {
            kind: ExprKind::If(Box::new(cond), Box::new(then), Box::new(other)),
            span,
        })
    }

    /// An `if` condition: an expression that does not start with `{` (the `{` opens the branch).
    fn expr_no_block(&mut self) -> PResult<Expr> {
        if self.is("{") {
            return Err(Diagnostic::new(self.span(), "expected a condition after 'if'"));
        }
        self.expr()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_functions_params_and_blocks() {
        let src = "param c: vec3 = [0, 0, 0]\nconst k = 2\n\
                   fn f(p: vec3, r: f32 = 1) -> f32 { let q = p - c; length(q) * k - r }\n\
                   render sphere_trace { size: 256, out: \"a.gif\", camera: surround(radius: 3, up: z) }";
        let s = parse(src, 0).unwrap();
        assert_eq!(s.items.len(), 4);
        let Item::Block(b) = &s.items[3] else {
            panic!("expected a block")
        };
        assert_eq!(b.entries.len(), 3);
        assert_eq!(b.name.as_ref().unwrap().name, "sphere_trace");
    }

    #[test]
    fn precedence_binds_mul_tighter() {
        let s = parse("fn f(x: f32) -> f32 = 1 + 2 * x", 0).unwrap();
        let Item::Fn(f) = &s.items[0] else { panic!() };
        let ExprKind::Binary(BinOp::Add, _, rhs) = &f.body.kind else {
            panic!("{:?}", f.body)
        };
        assert!(matches!(rhs.kind, ExprKind::Binary(BinOp::Mul, _, _)));
    }

    #[test]
    fn deep_nesting_is_an_error_not_a_crash() {
        let src = format!(
            "fn f(x: f32) -> f32 = {}x{}",
            "(".repeat(100_000),
            ")".repeat(100_000)
        );
        let err = parse(&src, 0).unwrap_err();
        assert!(err.message.contains("nested too deeply"), "{}", err.message);
        let src = format!("fn f(x: f32) -> f32 = {}x", "-".repeat(100_000));
        assert!(parse(&src, 0).is_err());
    }

    #[test]
    fn long_chains_are_an_error_not_a_crash() {
        let terms = |op: &str, n: usize| vec!["x"; n].join(op);
        for src in [
            format!("fn f(x: f32) -> f32 = {}", terms(" + ", 100_000)),
            format!("fn f(x: f32) -> f32 = {}", terms(" * ", 100_000)),
            format!("fn f(x: vec3) -> f32 = x{}.x", ".xyz".repeat(100_000)),
            format!("fn f(x: vec3) -> f32 = x{}", "[0]".repeat(100_000)),
            // Short chains, but nested: the lengths add up along the path.
            format!(
                "fn f(x: f32) -> f32 = {}x{}",
                format!("{} + (", terms(" + ", 80)).repeat(150),
                ")".repeat(150)
            ),
        ] {
            let err = parse(&src, 0).unwrap_err();
            assert!(err.message.contains("too long"), "{}", err.message);
            assert!(err.hint.as_deref().is_some_and(|h| h.contains("let")));
        }
        // Up to the limit, chains parse.
        let src = format!("fn f(x: f32) -> f32 = {}", terms(" + ", MAX_HEIGHT / 2));
        assert!(parse(&src, 0).is_ok());
    }
}
