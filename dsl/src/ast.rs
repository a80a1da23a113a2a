//! The syntax tree of a script, as the parser builds it. Every node keeps its span.

use crate::diag::Span;

/// A whole script: functions, params, constants and configuration blocks, in source order.
#[derive(Clone, Debug, Default)]
pub struct Script {
    /// The top-level items.
    pub items: Vec<Item>,
}

/// A name and where it was written.
#[derive(Clone, Debug, PartialEq)]
pub struct Ident {
    /// The name.
    pub name: String,
    /// Where it stands.
    pub span: Span,
}

/// A top-level item.
#[derive(Clone, Debug)]
pub enum Item {
    /// `fn name(args) -> type { body }`.
    Fn(FnDef),
    /// `param name: type = init`, a learnable value.
    Param(ParamDecl),
    /// `const name = expr`, a named constant that `--set` can override.
    Const(ConstDecl),
    /// `kind [name] { key: value, ... }`, e.g. `render sphere_trace { ... }` or `train { ... }`.
    Block(ConfigBlock),
}

/// A type as written, e.g. `f32`, `vec3`, `vec<39>`, `mat<128, 39>` or `(f32, vec3)`.
#[derive(Clone, Debug, PartialEq)]
pub struct TypeExpr {
    /// The type.
    pub ty: crate::types::Type,
    /// Where it was written.
    pub span: Span,
}

/// A user function definition.
#[derive(Clone, Debug)]
pub struct FnDef {
    /// The function's name.
    pub name: Ident,
    /// Its parameters.
    pub params: Vec<FnParam>,
    /// Its declared result type.
    pub ret: TypeExpr,
    /// The body expression.
    pub body: Expr,
}

/// One parameter of a user function, optionally with a default value.
#[derive(Clone, Debug)]
pub struct FnParam {
    /// The parameter's name.
    pub name: Ident,
    /// Its declared type.
    pub ty: TypeExpr,
    /// The value used when a call leaves it out.
    pub default: Option<Expr>,
}

/// A learnable parameter declaration.
#[derive(Clone, Debug)]
pub struct ParamDecl {
    /// The parameter's name.
    pub name: Ident,
    /// Its type (f32, a vector or a matrix).
    pub ty: TypeExpr,
    /// The initial value: a constant expression or an initializer such as `xavier(seed: 1)`.
    pub init: Expr,
}

/// A named constant.
#[derive(Clone, Debug)]
pub struct ConstDecl {
    /// The constant's name.
    pub name: Ident,
    /// Its value, a constant expression.
    pub value: Expr,
}

/// A configuration block: what to do with the script's functions.
#[derive(Clone, Debug)]
pub struct ConfigBlock {
    /// The block's kind, e.g. `render` or `train`.
    pub kind: Ident,
    /// An optional name after the kind, e.g. `sphere_trace` in `render sphere_trace { }`.
    pub name: Option<Ident>,
    /// The `key: value` entries.
    pub entries: Vec<ConfigEntry>,
    /// The whole block.
    pub span: Span,
}

/// One `key: value` entry of a configuration block; values are expressions.
#[derive(Clone, Debug)]
pub struct ConfigEntry {
    /// The key.
    pub key: Ident,
    /// The value.
    pub value: Expr,
}

/// An expression with its span.
#[derive(Clone, Debug)]
pub struct Expr {
    /// What kind of expression.
    pub kind: ExprKind,
    /// Where it stands.
    pub span: Span,
}

/// Unary operators.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UnOp {
    /// `-x`
    Neg,
    /// `!x` (1 where x is 0, else 0)
    Not,
}

/// Binary operators, from loosest to tightest binding: `||`, `&&`, comparisons, `+ -`, `* /`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BinOp {
    /// `+`
    Add,
    /// `-`
    Sub,
    /// `*`
    Mul,
    /// `/`
    Div,
    /// `<`
    Lt,
    /// `<=`
    Le,
    /// `>`
    Gt,
    /// `>=`
    Ge,
    /// `==`
    Eq,
    /// `!=`
    Ne,
    /// `&&`
    And,
    /// `||`
    Or,
}

impl BinOp {
    /// The operator as written.
    pub fn symbol(self) -> &'static str {
        match self {
            BinOp::Add => "+",
            BinOp::Sub => "-",
            BinOp::Mul => "*",
            BinOp::Div => "/",
            BinOp::Lt => "<",
            BinOp::Le => "<=",
            BinOp::Gt => ">",
            BinOp::Ge => ">=",
            BinOp::Eq => "==",
            BinOp::Ne => "!=",
            BinOp::And => "&&",
            BinOp::Or => "||",
        }
    }
}

/// A call argument, positional or named (`beta: 0.05`).
#[derive(Clone, Debug)]
pub struct Arg {
    /// The name for a named argument.
    pub name: Option<Ident>,
    /// The value.
    pub value: Expr,
}

/// A `let` binding's left-hand side: a name or a tuple of names.
#[derive(Clone, Debug)]
pub enum Pattern {
    /// `let x = ...`
    Name(Ident),
    /// `let (a, b) = ...`
    Tuple(Vec<Ident>),
}

/// A `let` statement inside a block.
#[derive(Clone, Debug)]
pub struct Let {
    /// What is bound.
    pub pattern: Pattern,
    /// The value.
    pub value: Expr,
}

/// The kinds of expression.
#[derive(Clone, Debug)]
pub enum ExprKind {
    /// A numeric literal.
    Number(f64),
    /// A string literal (configuration values only).
    Str(String),
    /// A variable, param or constant.
    Var(String),
    /// A unary operation.
    Unary(UnOp, Box<Expr>),
    /// A binary operation.
    Binary(BinOp, Box<Expr>, Box<Expr>),
    /// A call of a builtin or user function.
    Call(Ident, Vec<Arg>),
    /// A swizzle such as `p.xz`.
    Swizzle(Box<Expr>, Ident),
    /// Component `v[i]` of a vector.
    Index(Box<Expr>, Box<Expr>),
    /// Components `v[a..b]` of a vector.
    Slice(Box<Expr>, Box<Expr>, Box<Expr>),
    /// A vector literal `[a, b, c]`; vector arguments are concatenated.
    List(Vec<Expr>),
    /// A tuple `(a, b)`.
    Tuple(Vec<Expr>),
    /// `if c { a } else { b }`: both sides are evaluated, the result is selected per point.
    If(Box<Expr>, Box<Expr>, Box<Expr>),
    /// `{ let ...; expr }`.
    Block(Vec<Let>, Box<Expr>),
}
