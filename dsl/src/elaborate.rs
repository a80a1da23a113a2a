//! Type checking and lowering in one pass: expressions of the language become scalar IR values.
//!
//! User functions are inlined at each call (recursion is an error); vectors become one IR value per
//! component; `if` becomes a per-point select of both branches.

use std::collections::HashMap;

use crate::ast::*;
use crate::diag::{closest, Diagnostic, Span};
use crate::ir::{Graph, Op, V};
use crate::types::Type;
use crate::value::Val;

pub(crate) mod builtins;

/// The most nested user-function calls in one lowering.
pub const MAX_CALL_DEPTH: usize = 64;
/// The most IR nodes one lowering may create (the largest example takes 3,526; its gradient kernel about
/// 60 times more, and compiling a kernel takes time and memory that grow faster than its nodes).
pub const MAX_NODES: usize = 1 << 18;
/// The most expression nodes one lowering may visit (inlining can repeat a body many times).
pub const MAX_STEPS: usize = 1_000_000;
/// The most expression nodes the lowerings of one check of a script's functions may visit together:
/// many functions each just under [`MAX_STEPS`] must not add up to minutes of inlining.
pub const MAX_TOTAL_STEPS: usize = 4 * MAX_STEPS;

/// A learnable param as the lowering sees it.
#[derive(Clone, Debug)]
pub struct ParamSlot {
    /// Its type.
    pub ty: Type,
    /// Its first index in the flat param vector.
    pub offset: u32,
}

/// The names a function body can refer to besides its locals.
#[derive(Default)]
pub struct Globals<'a> {
    /// User and prelude functions.
    pub functions: HashMap<String, &'a FnDef>,
    /// Named constants.
    pub consts: HashMap<String, &'a Expr>,
    /// Learnable params.
    pub params: HashMap<String, ParamSlot>,
}

pub(crate) type EResult<T> = Result<T, Diagnostic>;

/// Lowers expressions into a graph.
pub struct Elaborator<'a, 'g> {
    /// The names visible everywhere.
    pub globals: &'a Globals<'a>,
    /// The graph being built.
    pub g: &'g mut Graph,
    scopes: Vec<HashMap<String, Val>>,
    call_stack: Vec<String>,
    steps: usize,
    /// The most steps this lowering may take: [`MAX_STEPS`], or less when a shared budget is nearly spent.
    max_steps: usize,
}

impl<'a, 'g> Elaborator<'a, 'g> {
    /// An elaborator adding to `g`.
    pub fn new(globals: &'a Globals<'a>, g: &'g mut Graph) -> Self {
        Elaborator {
            globals,
            g,
            scopes: vec![HashMap::new()],
            call_stack: Vec::new(),
            steps: 0,
            max_steps: MAX_STEPS,
        }
    }

    /// The same elaborator allowed at most `steps` expression steps (never more than [`MAX_STEPS`]): what
    /// is left of a budget that several lowerings share.
    pub fn with_max_steps(mut self, steps: usize) -> Self {
        self.max_steps = steps.min(MAX_STEPS);
        self
    }

    /// The expression steps taken so far.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// Lowers the body of `f` with its parameters bound to fresh inputs (in order, one per scalar).
    /// Returns the result coerced to the declared type.
    pub fn lower_entry(&mut self, f: &FnDef) -> EResult<Val> {
        let mut next_input = 0u32;
        let mut scope = HashMap::new();
        for p in &f.params {
            if let Type::Mat(..) | Type::Mlp(_) | Type::Grid(_) = p.ty.ty {
                return Err(Diagnostic::new(
                    p.ty.span,
                    format!(
                        "'{}' takes a matrix, so it can only be called from other functions",
                        f.name.name
                    ),
                )
                .with_hint("functions evaluated per point take f32, vectors and tuples"));
            }
            let n = p.ty.ty.scalars() as u32;
            let mut inputs = (next_input..next_input + n)
                .map(|i| self.g.input(i))
                .collect::<Vec<_>>()
                .into_iter();
            next_input += n;
            scope.insert(p.name.name.clone(), Val::unflatten(&p.ty.ty, &mut inputs));
        }
        self.call_stack.push(f.name.name.clone());
        let result = self.body(f, scope);
        self.call_stack.pop();
        result
    }

    fn body(&mut self, f: &FnDef, scope: HashMap<String, Val>) -> EResult<Val> {
        let saved = std::mem::replace(&mut self.scopes, vec![scope]);
        let result = self.expr(&f.body);
        self.scopes = saved;
        let v = result?;
        if !v.ty().coerces_to(&f.ret.ty) {
            return Err(Diagnostic::new(
                f.body.span,
                format!(
                    "'{}' declares result type {} but its body has type {}",
                    f.name.name,
                    f.ret.ty,
                    v.ty()
                ),
            )
            .with_hint("change the declared result type or the last expression of the body"));
        }
        Ok(v.coerce(&f.ret.ty))
    }

    fn tick(&mut self, span: Span) -> EResult<()> {
        self.steps += 1;
        if self.steps <= self.max_steps && self.g.len() <= MAX_NODES {
            return Ok(());
        }
        let limits = if self.max_steps < MAX_STEPS {
            format!("the script's functions together may take {MAX_TOTAL_STEPS} expression steps")
        } else {
            format!("the limits are {MAX_STEPS} expression steps and {MAX_NODES} IR nodes")
        };
        Err(Diagnostic::new(
            span,
            format!(
                "program too large after inlining, in {}",
                self.call_stack.join(" → ")
            ),
        )
        .with_hint(format!(
            "{limits}; each call repeats the body it calls, so functions calling others several times multiply"
        )))
    }

    /// Lowers one expression.
    pub fn expr(&mut self, e: &Expr) -> EResult<Val> {
        self.tick(e.span)?;
        match &e.kind {
            ExprKind::Number(n) => Ok(Val::Scalar(self.g.constant(*n))),
            ExprKind::Str(_) => Err(Diagnostic::new(e.span, "a string is not a value")
                .with_hint("strings are only allowed in configuration blocks")),
            ExprKind::Var(name) => self.var(name, e.span),
            ExprKind::Unary(op, a) => {
                let v = self.expr(a)?;
                let what = if *op == UnOp::Neg { "-" } else { "!" };
                self.map1(v, a.span, what, |g, x| match op {
                    UnOp::Neg => g.push(Op::Neg(x)),
                    UnOp::Not => {
                        let zero = g.constant(0.0);
                        g.push(Op::Eq(x, zero))
                    }
                })
            }
            ExprKind::Binary(op, a, b) => {
                let (va, vb) = (self.expr(a)?, self.expr(b)?);
                self.binary(*op, va, vb, e.span)
            }
            ExprKind::Call(name, args) => self.call(name, args, e.span),
            ExprKind::Swizzle(v, field) => {
                let v = self.expr(v)?;
                self.swizzle(v, field)
            }
            ExprKind::Index(v, i) => {
                let val = self.expr(v)?;
                let comps = self.vector(&val, v.span)?;
                let i = self.const_int(i, 0, comps.len().saturating_sub(1))?;
                Ok(Val::Scalar(comps[i]))
            }
            ExprKind::Slice(v, a, b) => {
                let val = self.expr(v)?;
                let comps = self.vector(&val, v.span)?;
                let start = self.const_int(a, 0, comps.len())?;
                let end = self.const_int(b, 0, comps.len())?;
                if end <= start {
                    return Err(Diagnostic::new(e.span, format!("empty slice {start}..{end}"))
                        .with_hint("a slice a..b takes components a to b-1, so b must exceed a"));
                }
                Ok(Val::Vector(comps[start..end].to_vec()))
            }
            ExprKind::List(items) => {
                let mut comps = Vec::new();
                for item in items {
                    let v = self.expr(item)?;
                    comps.extend(self.vector(&v, item.span)?);
                }
                if comps.is_empty() {
                    return Err(Diagnostic::new(e.span, "empty vector"));
                }
                Ok(Val::Vector(comps))
            }
            ExprKind::Tuple(items) => {
                let vals = items.iter().map(|i| self.expr(i)).collect::<EResult<Vec<_>>>()?;
                Ok(Val::Tuple(vals))
            }
            ExprKind::If(c, a, b) => {
                let cond = self.expr(c)?;
                let cond = match cond.coerce(&Type::F32) {
                    Val::Scalar(v) => v,
                    other => {
                        return Err(Diagnostic::new(
                            c.span,
                            format!("an 'if' condition must be f32, found {}", other.ty()),
                        ))
                    }
                };
                let (va, vb) = (self.expr(a)?, self.expr(b)?);
                if va.ty() != vb.ty() {
                    return Err(Diagnostic::new(
                        e.span,
                        format!("the branches of 'if' differ in type: {} and {}", va.ty(), vb.ty()),
                    ));
                }
                self.select(cond, va, vb, e.span)
            }
            ExprKind::Block(lets, value) => {
                self.scopes.push(HashMap::new());
                let result = self.block(lets, value);
                self.scopes.pop();
                result
            }
        }
    }

    fn block(&mut self, lets: &[Let], value: &Expr) -> EResult<Val> {
        for l in lets {
            let v = self.expr(&l.value)?;
            match &l.pattern {
                Pattern::Name(name) => self.bind(name, v)?,
                Pattern::Tuple(names) => {
                    let Val::Tuple(vals) = v else {
                        return Err(Diagnostic::new(
                            l.value.span,
                            format!("expected a tuple of {} values, found {}", names.len(), v.ty()),
                        ));
                    };
                    if vals.len() != names.len() {
                        return Err(Diagnostic::new(
                            l.value.span,
                            format!(
                                "expected a tuple of {} values, found {} values",
                                names.len(),
                                vals.len()
                            ),
                        ));
                    }
                    for (name, v) in names.iter().zip(vals) {
                        self.bind(name, v)?;
                    }
                }
            }
        }
        self.expr(value)
    }

    fn bind(&mut self, name: &Ident, v: Val) -> EResult<()> {
        let scope = self.scopes.last_mut().expect("a scope");
        if scope.contains_key(&name.name) {
            return Err(Diagnostic::new(
                name.span,
                format!("'{}' is already defined in this block", name.name),
            )
            .with_hint("choose another name"));
        }
        scope.insert(name.name.clone(), v);
        Ok(())
    }

    fn var(&mut self, name: &str, span: Span) -> EResult<Val> {
        if let Some(v) = self.scopes.iter().rev().find_map(|s| s.get(name)) {
            return Ok(v.clone());
        }
        if let Some(p) = self.globals.params.get(name) {
            let offset = p.offset;
            return Ok(match p.ty {
                Type::Mat(rows, cols) => Val::Matrix { offset, rows, cols },
                Type::Mlp(ref shape) => Val::Mlp {
                    offset,
                    shape: shape.clone(),
                },
                Type::Grid(ref shape) => Val::Grid {
                    offset,
                    shape: shape.clone(),
                },
                Type::Vec(n) => Val::Vector((0..n as u32).map(|i| self.g.param(offset + i)).collect()),
                _ => Val::Scalar(self.g.param(offset)),
            });
        }
        if let Some(&value) = self.globals.consts.get(name) {
            let key = format!("const {name}");
            if self.call_stack.contains(&key) {
                return Err(Diagnostic::new(
                    span,
                    format!("constant '{name}' is defined in terms of itself"),
                ));
            }
            self.call_stack.push(key);
            let saved = std::mem::replace(&mut self.scopes, vec![HashMap::new()]);
            let result = self.expr(value);
            self.scopes = saved;
            self.call_stack.pop();
            return result;
        }
        let mut d = Diagnostic::new(span, format!("unknown name '{name}'"));
        let locals = self.scopes.iter().flat_map(|s| s.keys().map(String::as_str));
        let globals = self
            .globals
            .params
            .keys()
            .chain(self.globals.consts.keys())
            .map(String::as_str);
        if let Some(c) = closest(name, locals.chain(globals)) {
            d = d.with_hint(format!("did you mean '{c}'?"));
        } else if self.globals.functions.contains_key(name) || builtins::is_builtin(name) {
            d = d.with_hint(format!(
                "'{name}' is a function: call it with arguments, e.g. '{name}(p)'"
            ));
        }
        Err(d)
    }

    /// The components of a scalar or vector value, or a type error.
    pub fn vector(&self, v: &Val, span: Span) -> EResult<Vec<V>> {
        v.components()
            .ok_or_else(|| Diagnostic::new(span, format!("expected f32 or a vector, found {}", v.ty())))
    }

    /// A compile-time integer in `lo..=hi`.
    pub fn const_int(&mut self, e: &Expr, lo: usize, hi: usize) -> EResult<usize> {
        let v = self.expr(e)?;
        let value = match v {
            Val::Scalar(s) => self.g.const_value(s),
            _ => None,
        };
        match value {
            Some(x) if x.fract() == 0.0 && x >= lo as f64 && x <= hi as f64 => Ok(x as usize),
            Some(x) => Err(Diagnostic::new(e.span, format!("{x} is out of range"))
                .with_hint(format!("expected a whole number from {lo} to {hi}"))),
            None => Err(Diagnostic::new(e.span, "expected a constant whole number")
                .with_hint("indices, slice bounds and sizes must be known before the script runs")),
        }
    }

    fn swizzle(&mut self, v: Val, field: &Ident) -> EResult<Val> {
        let comps = self.vector(&v, field.span)?;
        let mut out = Vec::new();
        for ch in field.name.chars() {
            let idx = match ch {
                'x' | 'r' => 0,
                'y' | 'g' => 1,
                'z' | 'b' => 2,
                'w' | 'a' => 3,
                _ => usize::MAX,
            };
            if idx >= comps.len() || field.name.len() > 4 {
                let available = &"xyzw"[..comps.len().min(4)];
                return Err(Diagnostic::new(
                    field.span,
                    format!("unknown swizzle '.{}' on a value of type {}", field.name, v.ty()),
                )
                .with_hint(format!(
                    "swizzles combine up to 4 of the letters '{available}'; use v[i] or v[a..b] for longer vectors"
                )));
            }
            out.push(comps[idx]);
        }
        Ok(if out.len() == 1 {
            Val::Scalar(out[0])
        } else {
            Val::Vector(out)
        })
    }

    /// Applies `f` to each component of a scalar or vector.
    pub fn map1(
        &mut self,
        v: Val,
        span: Span,
        what: &str,
        mut f: impl FnMut(&mut Graph, V) -> V,
    ) -> EResult<Val> {
        match v {
            Val::Scalar(x) => Ok(Val::Scalar(f(self.g, x))),
            Val::Vector(xs) => Ok(Val::Vector(xs.into_iter().map(|x| f(self.g, x)).collect())),
            other => Err(Diagnostic::new(
                span,
                format!("'{what}' needs f32 or a vector, found {}", other.ty()),
            )),
        }
    }

    /// Applies `f` componentwise to values of equal shape, a scalar standing for any vector.
    pub fn map_n(
        &mut self,
        vals: &[Val],
        span: Span,
        what: &str,
        mut f: impl FnMut(&mut Graph, &[V]) -> V,
    ) -> EResult<Val> {
        let mut width: Option<usize> = None;
        for v in vals {
            match v {
                Val::Scalar(_) => {}
                Val::Vector(xs) => {
                    match width {
                        Some(w) if w != xs.len() => {
                            let types: Vec<String> = vals.iter().map(|v| v.ty().to_string()).collect();
                            return Err(Diagnostic::new(
                            span,
                            format!("mismatched types for '{what}': {}", types.join(" and ")),
                        )
                        .with_hint("vectors combine componentwise only with vectors of the same length or with f32"));
                        }
                        _ => width = Some(xs.len()),
                    }
                }
                other => {
                    return Err(Diagnostic::new(
                        span,
                        format!("'{what}' needs f32 or vectors, found {}", other.ty()),
                    ))
                }
            }
        }
        let comp = |v: &Val, i: usize| match v {
            Val::Scalar(x) => *x,
            Val::Vector(xs) => xs[i],
            _ => unreachable!("checked above"),
        };
        let mut args = Vec::with_capacity(vals.len());
        let mut one = |g: &mut Graph, i: usize| {
            args.clear();
            args.extend(vals.iter().map(|v| comp(v, i)));
            f(g, &args)
        };
        Ok(match width {
            None => Val::Scalar(one(self.g, 0)),
            Some(w) => Val::Vector((0..w).map(|i| one(self.g, i)).collect()),
        })
    }

    fn binary(&mut self, op: BinOp, a: Val, b: Val, span: Span) -> EResult<Val> {
        self.map_n(&[a, b], span, op.symbol(), |g, x| {
            let (a, b) = (x[0], x[1]);
            match op {
                BinOp::Add => g.push(Op::Add(a, b)),
                BinOp::Sub => g.push(Op::Sub(a, b)),
                BinOp::Mul => g.push(Op::Mul(a, b)),
                BinOp::Div => g.push(Op::Div(a, b)),
                BinOp::Lt => g.push(Op::Lt(a, b)),
                BinOp::Le => g.push(Op::Le(a, b)),
                BinOp::Gt => g.push(Op::Lt(b, a)),
                BinOp::Ge => g.push(Op::Le(b, a)),
                BinOp::Eq => g.push(Op::Eq(a, b)),
                BinOp::Ne => {
                    let eq = g.push(Op::Eq(a, b));
                    let one = g.constant(1.0);
                    g.push(Op::Sub(one, eq))
                }
                BinOp::And | BinOp::Or => {
                    let (zero, one) = (g.constant(0.0), g.constant(1.0));
                    let b_is_zero = g.push(Op::Eq(b, zero));
                    let b_true = g.push(Op::Sub(one, b_is_zero));
                    if op == BinOp::And {
                        g.push(Op::Select(a, b_true, zero))
                    } else {
                        g.push(Op::Select(a, one, b_true))
                    }
                }
            }
        })
    }

    /// Per-point selection between two values of the same type.
    pub fn select(&mut self, cond: V, a: Val, b: Val, span: Span) -> EResult<Val> {
        match (a, b) {
            (Val::Tuple(xs), Val::Tuple(ys)) => Ok(Val::Tuple(
                xs.into_iter()
                    .zip(ys)
                    .map(|(x, y)| self.select(cond, x, y, span))
                    .collect::<EResult<_>>()?,
            )),
            (a, b) => self.map_n(&[a, b], span, "if", |g, x| g.push(Op::Select(cond, x[0], x[1]))),
        }
    }

    fn call(&mut self, name: &Ident, args: &[Arg], span: Span) -> EResult<Val> {
        if let Some(&f) = self.globals.functions.get(&name.name) {
            return self.call_user(f, name, args, span);
        }
        if builtins::is_builtin(&name.name) {
            if let Some(named) = args.iter().find_map(|a| a.name.as_ref()) {
                return Err(Diagnostic::new(
                    named.span,
                    format!("builtin '{}' takes no named arguments", name.name),
                )
                .with_hint(format!("write {}", builtins::signature(&name.name))));
            }
            let mut vals = Vec::with_capacity(args.len());
            for a in args {
                vals.push((self.expr(&a.value)?, a.value.span));
            }
            return builtins::call(self, name, vals, span);
        }
        if builtins::is_initializer(&name.name) {
            return Err(
                Diagnostic::new(name.span, format!("'{}' can only initialize a param", name.name))
                    .with_hint(format!("write e.g. 'param w: mat<64, 3> = {}(...)'", name.name)),
            );
        }
        let known = self
            .globals
            .functions
            .keys()
            .map(String::as_str)
            .chain(builtins::NAMES.iter().copied());
        let mut d = Diagnostic::new(name.span, format!("unknown function '{}'", name.name));
        if let Some(c) = closest(&name.name, known) {
            d = d.with_hint(format!("did you mean '{c}'?"));
        }
        Err(d)
    }

    fn call_user(&mut self, f: &FnDef, name: &Ident, args: &[Arg], span: Span) -> EResult<Val> {
        if self.call_stack.contains(&f.name.name) {
            return Err(
                Diagnostic::new(name.span, format!("recursive call to '{}'", f.name.name))
                    .with_hint("functions are inlined into each caller, so they cannot call themselves"),
            );
        }
        if self.call_stack.len() >= MAX_CALL_DEPTH {
            return Err(Diagnostic::new(name.span, "calls nested too deeply")
                .with_hint(format!("the limit is {MAX_CALL_DEPTH} nested calls")));
        }
        let signature = || {
            let ps: Vec<String> = f
                .params
                .iter()
                .map(|p| format!("{}: {}", p.name.name, p.ty.ty))
                .collect();
            format!("{}({}) -> {}", f.name.name, ps.join(", "), f.ret.ty)
        };
        let mut slots: Vec<Option<&Arg>> = vec![None; f.params.len()];
        let mut positional = 0;
        for a in args {
            let idx = match &a.name {
                None => {
                    if positional >= f.params.len() {
                        return Err(Diagnostic::new(
                            a.value.span,
                            format!("too many arguments: '{}' takes {}", f.name.name, f.params.len()),
                        )
                        .with_hint(signature()));
                    }
                    positional += 1;
                    positional - 1
                }
                Some(n) => f
                    .params
                    .iter()
                    .position(|p| p.name.name == n.name)
                    .ok_or_else(|| {
                        Diagnostic::new(n.span, format!("'{}' has no parameter '{}'", f.name.name, n.name))
                            .with_hint(signature())
                    })?,
            };
            if slots[idx].is_some() {
                return Err(Diagnostic::new(
                    a.value.span,
                    format!("parameter '{}' is given twice", f.params[idx].name.name),
                ));
            }
            slots[idx] = Some(a);
        }
        // Arguments are lowered in the caller's scope; defaults in the callee's, after earlier params.
        let mut scope: HashMap<String, Val> = HashMap::new();
        for (p, slot) in f.params.iter().zip(slots) {
            let (v, at) = match (slot, &p.default) {
                (Some(a), _) => (self.expr(&a.value)?, a.value.span),
                (None, Some(d)) => {
                    let saved = std::mem::replace(&mut self.scopes, vec![scope.clone()]);
                    let v = self.expr(d);
                    self.scopes = saved;
                    (v?, d.span)
                }
                (None, None) => {
                    return Err(Diagnostic::new(
                        span,
                        format!("missing argument '{}' of '{}'", p.name.name, f.name.name),
                    )
                    .with_hint(signature()))
                }
            };
            let v = match (v, &p.ty.ty) {
                (Val::Scalar(s), Type::Vec(n)) if *n > 1 => Val::Vector(vec![s; *n]),
                (v, _) => v,
            };
            if !v.ty().coerces_to(&p.ty.ty) {
                return Err(Diagnostic::new(
                    at,
                    format!(
                        "argument '{}' of '{}' must be {}, found {}",
                        p.name.name,
                        f.name.name,
                        p.ty.ty,
                        v.ty()
                    ),
                )
                .with_hint(signature()));
            }
            scope.insert(p.name.name.clone(), v.coerce(&p.ty.ty));
        }
        self.call_stack.push(f.name.name.clone());
        let result = self.body(f, scope);
        self.call_stack.pop();
        result
    }
}
