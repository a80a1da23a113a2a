//! A checked program: a script with the prelude, its params with initial values, and lowering of any of
//! its functions to IR.

use std::collections::HashMap;

use crate::ast::*;
use crate::budget;
use crate::diag::{Diagnostic, Report, SourceMap, Span};
use crate::elaborate::builtins;
use crate::elaborate::{Elaborator, Globals, ParamSlot, MAX_TOTAL_STEPS};
use crate::init::Initializer;
use crate::ir::Graph;
use crate::parser::parse;
use crate::types::Type;
use crate::value::Val;

/// The standard library, written in the language itself.
pub const PRELUDE: &str = include_str!("../prelude.sdf");

/// The kinds of configuration block a script may hold.
pub const BLOCK_KINDS: &[&str] = &["render", "train", "mesh", "bake", "viz"];

/// A learnable param of a program.
#[derive(Clone, Debug)]
pub struct ParamInfo {
    /// Its name.
    pub name: String,
    /// Its type.
    pub ty: Type,
    /// Its first index in the flat param vector (matrices are row-major).
    pub offset: usize,
}

/// A function's signature.
#[derive(Clone, Debug, PartialEq)]
pub struct Signature {
    /// The function's name.
    pub name: String,
    /// Parameter names and types, in order.
    pub inputs: Vec<(String, Type)>,
    /// The result type.
    pub output: Type,
}

impl std::fmt::Display for Signature {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let ps: Vec<String> = self.inputs.iter().map(|(n, t)| format!("{n}: {t}")).collect();
        write!(f, "fn {}({}) -> {}", self.name, ps.join(", "), self.output)
    }
}

/// A function lowered to IR: one graph input per scalar of its parameters, one output per scalar of its
/// result.
#[derive(Clone, Debug)]
pub struct Lowered {
    /// The function's signature.
    pub signature: Signature,
    /// The graph.
    pub graph: Graph,
}

/// A parsed and type-checked script, with the prelude.
#[derive(Debug)]
pub struct Program {
    /// The prelude and the script, for diagnostics.
    pub sources: SourceMap,
    prelude: Script,
    script: Script,
    /// The learnable params, in declaration order.
    pub params: Vec<ParamInfo>,
    /// The initial value of every param scalar, concatenated in the order of `params`.
    pub param_values: Vec<f32>,
}

/// Parses and checks `source` (named `file` in diagnostics).
pub fn compile(file: &str, source: &str) -> Result<Program, Report> {
    compile_with(file, source, &[])
}

/// Parses and checks `source` after applying `overrides`, each `name=value` (a `const`) or
/// `block.key=value` (a setting of the first block of that kind or name, e.g. `train.steps=100`,
/// `render.size=64` or `volume.size=64`, or of the i-th with `render[1].size=64`); the values are
/// expressions of the language. Errors in an override point at it.
pub fn compile_with(file: &str, source: &str, overrides: &[String]) -> Result<Program, Report> {
    let mut sources = SourceMap::default();
    sources.add("<prelude>", PRELUDE);
    let base = sources.add(file, source);
    let fail = |sources: &SourceMap, diagnostics| Report {
        sources: sources.clone(),
        diagnostics,
    };
    let prelude = parse(PRELUDE, 0).map_err(|d| fail(&sources, vec![d]))?;
    let mut script = parse(source, base).map_err(|d| fail(&sources, vec![d]))?;
    for text in overrides {
        let at = sources.add("--set", text);
        crate::overrides::apply(&mut script, text, at).map_err(|d| fail(&sources, vec![d]))?;
    }
    let mut program = Program {
        sources,
        prelude,
        script,
        params: Vec::new(),
        param_values: Vec::new(),
    };
    let mut diagnostics = program.check_names();
    diagnostics.extend(program.check_consts());
    diagnostics.extend(program.init_params());
    if diagnostics.is_empty() {
        diagnostics.extend(program.check_functions());
    }
    if diagnostics.is_empty() {
        Ok(program)
    } else {
        diagnostics.sort_by_key(|d| (d.span.start, d.span.end));
        diagnostics.dedup();
        Err(fail(&program.sources, diagnostics))
    }
}

/// Checking a script's functions stops after this many errors (each may search every name for a "did you
/// mean", so a script of thousands of broken functions would take quadratic time to report them all).
const MAX_FUNCTION_ERRORS: usize = 100;

impl Program {
    fn user_items(&self) -> impl Iterator<Item = &Item> {
        self.script.items.iter()
    }

    fn fn_defs(&self) -> impl Iterator<Item = &FnDef> {
        self.prelude
            .items
            .iter()
            .chain(&self.script.items)
            .filter_map(|i| match i {
                Item::Fn(f) => Some(f),
                _ => None,
            })
    }

    /// The names every function body sees: user functions shadow prelude ones.
    fn globals(&self) -> Globals<'_> {
        let mut g = Globals::default();
        for f in self.fn_defs() {
            g.functions.insert(f.name.name.clone(), f);
        }
        for item in self.user_items() {
            if let Item::Const(c) = item {
                g.consts.insert(c.name.name.clone(), &c.value);
            }
        }
        for p in &self.params {
            g.params.insert(
                p.name.clone(),
                ParamSlot {
                    ty: p.ty.clone(),
                    offset: p.offset as u32,
                },
            );
        }
        g
    }

    fn check_names(&self) -> Vec<Diagnostic> {
        let mut diagnostics = Vec::new();
        let mut fns: HashMap<&str, Span> = HashMap::new();
        let mut values: HashMap<&str, Span> = HashMap::new();
        for item in self.user_items() {
            let (name, table) = match item {
                Item::Fn(f) => (&f.name, &mut fns),
                Item::Param(p) => (&p.name, &mut values),
                Item::Const(c) => (&c.name, &mut values),
                Item::Block(b) => {
                    if !BLOCK_KINDS.contains(&b.kind.name.as_str()) {
                        let mut d = Diagnostic::new(b.kind.span, format!("unknown block '{}'", b.kind.name));
                        d = match crate::diag::closest(&b.kind.name, BLOCK_KINDS.iter().copied()) {
                            Some(c) => d.with_hint(format!("did you mean '{c}'?")),
                            None => d.with_hint(format!("blocks are: {}", BLOCK_KINDS.join(", "))),
                        };
                        diagnostics.push(d);
                    }
                    continue;
                }
            };
            if builtins::is_builtin(&name.name) || builtins::is_initializer(&name.name) {
                diagnostics.push(
                    Diagnostic::new(name.span, format!("'{}' is the name of a builtin", name.name))
                        .with_hint("choose another name"),
                );
            } else if let Some(first) = table.insert(&name.name, name.span) {
                let (line, _) = self.line_of(first);
                diagnostics.push(
                    Diagnostic::new(name.span, format!("duplicate name '{}'", name.name))
                        .with_hint(format!("'{}' is already defined on line {line}", name.name)),
                );
            }
        }
        diagnostics
    }

    fn line_of(&self, span: Span) -> (usize, usize) {
        match self.sources.file_at(span.start as usize) {
            Some(f) => crate::diag::line_col(&f.text, span.start as usize - f.base),
            None => (0, 0),
        }
    }

    fn init_params(&mut self) -> Vec<Diagnostic> {
        let decls: Vec<ParamDecl> = self
            .user_items()
            .filter_map(|i| match i {
                Item::Param(p) => Some(p.clone()),
                _ => None,
            })
            .collect();
        let mut diagnostics = Vec::new();
        let mut floats = 0u64;
        for (index, decl) in decls.iter().enumerate() {
            floats = floats.saturating_add(decl.ty.ty.scalars() as u64);
            let what = || format!("the params up to '{}' ({floats} floats)", decl.name.name);
            if let Err(e) = budget::check(what, budget::bytes_of(floats, 4)) {
                diagnostics.push(Diagnostic::new(decl.ty.span, e.to_string()).with_hint(budget::HINT));
                break;
            }
            let offset = self.param_values.len();
            match self.initial_value(decl, index) {
                Ok(values) => {
                    self.param_values.extend(values);
                    self.params.push(ParamInfo {
                        name: decl.name.name.clone(),
                        ty: decl.ty.ty.clone(),
                        offset,
                    });
                }
                Err(d) => diagnostics.push(d),
            }
        }
        diagnostics
    }

    /// Each `const` whose value is not finite (as an f32), at its value, and each block setting that uses
    /// such a const, at the setting (naming the const's line and column).
    fn check_consts(&self) -> Vec<Diagnostic> {
        let mut diagnostics = Vec::new();
        let mut bad = Vec::new();
        for item in self.user_items() {
            if let Item::Const(c) = item {
                let Ok(values) = self.constant_values(&c.value) else {
                    continue;
                };
                if let Err(d) = finite(c.value.span, &values) {
                    diagnostics.push(d);
                    bad.push(&c.name);
                }
            }
        }
        for block in self.blocks() {
            for entry in &block.entries {
                let Some(name) = bad.iter().find(|n| mentions(&entry.value, &n.name)) else {
                    continue;
                };
                let (line, col) = self.line_of(name.span);
                diagnostics.push(
                    Diagnostic::new(
                        entry.value.span,
                        format!(
                            "setting '{}' is not finite: it uses const '{}', whose value is not a finite 32-bit float",
                            entry.key.name, name.name
                        ),
                    )
                    .with_hint(format!("'{}' is defined at line {line}, column {col}", name.name)),
                );
            }
        }
        diagnostics.sort_by_key(|d| d.span.start);
        diagnostics
    }

    /// Evaluates `e` to finite constants (consts are visible, params are not).
    fn constant(&self, e: &Expr) -> Result<Vec<f64>, Diagnostic> {
        let values = self.constant_values(e)?;
        finite(e.span, &values)?;
        Ok(values)
    }

    /// Evaluates `e` to constants, finite or not.
    fn constant_values(&self, e: &Expr) -> Result<Vec<f64>, Diagnostic> {
        let globals = Globals {
            params: HashMap::new(),
            ..self.globals()
        };
        let mut g = Graph::new();
        let v = Elaborator::new(&globals, &mut g).expr(e)?;
        let scalars = v
            .flatten()
            .ok_or_else(|| Diagnostic::new(e.span, format!("expected a constant, found {}", v.ty())))?;
        scalars
            .iter()
            .map(|&s| g.const_value(s))
            .collect::<Option<Vec<f64>>>()
            .ok_or_else(|| {
                Diagnostic::new(e.span, "expected a constant value")
                    .with_hint("a param's initial value cannot depend on inputs or params")
            })
    }

    fn initial_value(&self, decl: &ParamDecl, index: usize) -> Result<Vec<f32>, Diagnostic> {
        let ty = &decl.ty.ty;
        if let Type::Tuple(_) = ty {
            return Err(Diagnostic::new(decl.ty.span, "a param cannot be a tuple")
                .with_hint("declare one param per value"));
        }
        let count = ty.scalars();
        if let ExprKind::Call(name, args) = &decl.init.kind {
            if builtins::is_initializer(&name.name) {
                return self.random_init(decl, name, args, index);
            }
        }
        let values = self.constant(&decl.init)?;
        match values.len() {
            1 => Ok(vec![values[0] as f32; count]),
            n if n == count && !matches!(ty, Type::Mat(..) | Type::Mlp(_) | Type::Grid(_)) => {
                Ok(values.iter().map(|&x| x as f32).collect())
            }
            n => Err(Diagnostic::new(
                decl.init.span,
                format!("param '{}' of type {ty} cannot start from a value of {n} components", decl.name.name),
            )
            .with_hint("give one value to repeat, a vector of the same length, or an initializer such as xavier(seed: 1)")),
        }
    }

    fn random_init(
        &self,
        decl: &ParamDecl,
        name: &Ident,
        args: &[Arg],
        index: usize,
    ) -> Result<Vec<f32>, Diagnostic> {
        let ty = &decl.ty.ty;
        let mut positional = Vec::new();
        let mut named = HashMap::new();
        for a in args {
            let v = self.constant(&a.value)?;
            if v.len() != 1 {
                return Err(Diagnostic::new(a.value.span, "initializer arguments are numbers"));
            }
            match &a.name {
                Some(n) => {
                    named.insert(n.name.as_str(), (v[0], n.span));
                }
                None => positional.push(v[0]),
            }
        }
        let allowed: &[&str] = match name.name.as_str() {
            "uniform" | "normal" => &["seed"],
            _ => &["seed", "fan_in"],
        };
        if let Some((key, (_, span))) = named.iter().find(|(k, _)| !allowed.contains(k)) {
            return Err(
                Diagnostic::new(*span, format!("'{}' has no argument '{key}'", name.name))
                    .with_hint(format!("its named arguments are: {}", allowed.join(", "))),
            );
        }
        let seed = match named.get("seed") {
            Some(&(value, span)) => whole_argument("seed", value, span, 0)?,
            None => index as u64 + 1,
        };
        if let Some(&(value, span)) = named.get("fan_in") {
            // A fan-in of 0 divides by zero: every weight would be NaN or infinite.
            whole_argument("fan_in", value, span, 1)?;
        }
        if let Type::Mlp(shape) = ty {
            if let Some((_, span)) = named.get("fan_in") {
                return Err(Diagnostic::new(*span, "an mlp knows each layer's fan_in"));
            }
            return mlp_init(shape, name, &positional, seed);
        }
        let (fan_out, fan_in) = match ty {
            Type::Mat(r, c) => (Some(*r as f64), named.get("fan_in").map_or(*c as f64, |f| f.0)),
            _ => (None, named.get("fan_in").map_or(f64::NAN, |f| f.0)),
        };
        let init = initializer(name, &positional, fan_in, fan_out, ty)?;
        Ok(init.sample(ty.scalars(), seed))
    }

    /// The functions' type errors, up to `MAX_FUNCTION_ERRORS` (checking stops there).
    fn check_functions(&self) -> Vec<Diagnostic> {
        let globals = self.globals();
        let mut diagnostics = Vec::new();
        // Inlining steps of all the functions so far, against `MAX_TOTAL_STEPS`.
        let mut spent = 0;
        for f in self.fn_defs() {
            if diagnostics.len() == MAX_FUNCTION_ERRORS || spent > MAX_TOTAL_STEPS {
                break;
            }
            let mut g = Graph::new();
            let mut elaborator = Elaborator::new(&globals, &mut g).with_max_steps(MAX_TOTAL_STEPS - spent);
            let checked = elaborator.check_fn(f);
            spent += elaborator.steps();
            if let Err(d) = checked {
                diagnostics.push(d);
            }
        }
        diagnostics
    }

    /// The signatures of the script's own functions (not the prelude's), in source order.
    pub fn functions(&self) -> Vec<Signature> {
        self.user_items()
            .filter_map(|i| match i {
                Item::Fn(f) => Some(signature(f)),
                _ => None,
            })
            .collect()
    }

    /// The signature of function `name` (script or prelude).
    pub fn signature(&self, name: &str) -> Option<Signature> {
        self.globals().functions.get(name).map(|f| signature(f))
    }

    /// The configuration blocks of the script, in source order.
    pub fn blocks(&self) -> Vec<&ConfigBlock> {
        self.user_items()
            .filter_map(|i| match i {
                Item::Block(b) => Some(b),
                _ => None,
            })
            .collect()
    }

    /// The number of param scalars.
    pub fn n_params(&self) -> usize {
        self.param_values.len()
    }

    /// The error for function `name`, which the script lacks, named at `span` (`Span::NOWHERE` when a
    /// command line names it), with the closest function as a hint.
    pub fn no_function(&self, name: &str, span: Span) -> Diagnostic {
        let names: Vec<String> = self.functions().into_iter().map(|s| s.name).collect();
        let d = Diagnostic::new(span, format!("no function '{name}' in the script"));
        match crate::diag::closest(name, names.iter().map(String::as_str)) {
            Some(c) => d.with_hint(format!("did you mean '{c}'?")),
            None => d.with_hint(format!("the script defines: {}", names.join(", "))),
        }
    }

    /// Lowers function `name` to IR (outputs are the result's scalars).
    pub fn lower(&self, name: &str) -> Result<Lowered, Report> {
        let globals = self.globals();
        let report = |diagnostics| Report {
            sources: self.sources.clone(),
            diagnostics,
        };
        let Some(&f) = globals.functions.get(name) else {
            return Err(report(vec![self.no_function(name, Span::NOWHERE)]));
        };
        let mut graph = Graph::new();
        let result = Elaborator::new(&globals, &mut graph)
            .lower_entry(f)
            .map_err(|d| report(vec![d]))?;
        let sig = signature(f);
        graph.n_inputs = sig.inputs.iter().map(|(_, t)| t.scalars() as u32).sum();
        graph.outputs = result.flatten().unwrap_or_default();
        Ok(Lowered {
            signature: sig,
            graph: graph.compact(),
        })
    }

    /// Lowers several functions into one graph whose outputs are theirs, concatenated. Functions share the
    /// graph's inputs from the first: `density(p)` and `color(p, d)` read inputs 0..3 for `p`, and `color`'s
    /// `d` reads 3..6. Common subexpressions of the functions are computed once.
    pub fn lower_many(&self, names: &[&str]) -> Result<Lowered, Report> {
        let mut graph = Graph::new();
        let mut outputs = Vec::new();
        let mut widest: Option<Signature> = None;
        let mut results = Vec::new();
        for name in names {
            let f = self.lower(name)?;
            let sig = f.signature.clone();
            let globals = self.globals();
            let def = globals.functions[*name];
            let v = Elaborator::new(&globals, &mut graph)
                .lower_entry(def)
                .map_err(|d| Report {
                    sources: self.sources.clone(),
                    diagnostics: vec![d],
                })?;
            outputs.extend(v.flatten().unwrap_or_default());
            results.push(sig.output.clone());
            if widest.as_ref().is_none_or(|w| sig.inputs.len() > w.inputs.len()) {
                widest = Some(sig);
            }
        }
        let mut signature = widest.expect("at least one function");
        signature.name = names.join("+");
        signature.output = Type::Tuple(results);
        graph.n_inputs = signature.inputs.iter().map(|(_, t)| t.scalars() as u32).sum();
        graph.outputs = outputs;
        Ok(Lowered {
            signature,
            graph: graph.compact(),
        })
    }

    /// The script's `const`s whose value is one number, with that value, in source order (the live
    /// viewer's sliders).
    pub fn scalar_consts(&self) -> Vec<(String, f64)> {
        self.user_items()
            .filter_map(|item| match item {
                Item::Const(c) => match self.constant(&c.value).ok()?.as_slice() {
                    [x] => Some((c.name.name.clone(), *x)),
                    _ => None,
                },
                _ => None,
            })
            .collect()
    }

    /// Lowers a standalone constant expression in the context of this program (consts visible).
    pub fn eval_constant(&self, e: &Expr) -> Result<Vec<f64>, Diagnostic> {
        self.constant(e)
    }
}

/// Whether expression `e` refers to the variable, param or const `name` anywhere.
fn mentions(e: &Expr, name: &str) -> bool {
    let any = |items: &[Expr]| items.iter().any(|x| mentions(x, name));
    match &e.kind {
        ExprKind::Number(_) | ExprKind::Str(_) => false,
        ExprKind::Var(v) => v == name,
        ExprKind::Unary(_, a) | ExprKind::Swizzle(a, _) => mentions(a, name),
        ExprKind::Binary(_, a, b) | ExprKind::Index(a, b) => mentions(a, name) || mentions(b, name),
        ExprKind::Slice(a, b, c) | ExprKind::If(a, b, c) => {
            mentions(a, name) || mentions(b, name) || mentions(c, name)
        }
        ExprKind::Call(_, args) => args.iter().any(|a| mentions(&a.value, name)),
        ExprKind::List(items) | ExprKind::Tuple(items) => any(items),
        ExprKind::Block(lets, value) => {
            lets.iter().any(|l| mentions(&l.value, name)) || mentions(value, name)
        }
    }
}

/// Fails unless every value is a finite f32 (NaN from 0/0, or beyond ±3.4e38, would poison every
/// result that uses it).
fn finite(span: Span, values: &[f64]) -> Result<(), Diagnostic> {
    match values.iter().find(|x| !(**x as f32).is_finite()) {
        None => Ok(()),
        Some(x) => {
            let what = if x.is_nan() {
                "NaN".to_string()
            } else {
                format!("{x:e}")
            };
            let at = if values.len() > 1 {
                " (one of its components)"
            } else {
                ""
            };
            Err(Diagnostic::new(
                span,
                format!("this value is {what}{at}, not a finite 32-bit float"),
            )
            .with_hint("look for a division by zero, or a number beyond ±3.4e38"))
        }
    }
}

fn signature(f: &FnDef) -> Signature {
    Signature {
        name: f.name.name.clone(),
        inputs: f
            .params
            .iter()
            .map(|p| (p.name.name.clone(), p.ty.ty.clone()))
            .collect(),
        output: f.ret.ty.clone(),
    }
}

impl Elaborator<'_, '_> {
    /// Type-checks `f`, lowering it with fresh inputs (matrix params are bound to a placeholder matrix).
    pub fn check_fn(&mut self, f: &FnDef) -> Result<Val, Diagnostic> {
        if f.params
            .iter()
            .any(|p| matches!(p.ty.ty, Type::Mat(..) | Type::Mlp(_) | Type::Grid(_)))
        {
            // Functions taking a matrix are checked where they are called with a real matrix param.
            return Ok(Val::Tuple(vec![]));
        }
        self.lower_entry(f)
    }
}

/// The largest initializer argument taken as a whole number: every integer up to it is exact in an f64.
const MAX_WHOLE_ARGUMENT: f64 = 9_007_199_254_740_992.0;

/// Initializer argument `key` (its `value` written at `span`) as a whole number of at least `lo`.
fn whole_argument(key: &str, value: f64, span: Span, lo: u64) -> Result<u64, Diagnostic> {
    if value.fract() == 0.0 && value >= lo as f64 && value <= MAX_WHOLE_ARGUMENT {
        return Ok(value as u64);
    }
    Err(Diagnostic::new(
        span,
        format!("{key} is {value}, not a whole number from {lo} to 2^53"),
    )
    .with_hint(format!("write e.g. {key}: {}", lo.max(1))))
}

/// The distribution of initializer `name` (with its positional arguments) for a block of `fan_in` inputs
/// and `fan_out` outputs (None for a vector) of type `ty`.
fn initializer(
    name: &Ident,
    positional: &[f64],
    fan_in: f64,
    fan_out: Option<f64>,
    ty: &Type,
) -> Result<Initializer, Diagnostic> {
    let expect = |n: usize| -> Result<(), Diagnostic> {
        if positional.len() == n {
            Ok(())
        } else {
            Err(Diagnostic::new(
                name.span,
                format!(
                    "wrong number of arguments: '{}' takes {n} besides seed, got {}",
                    name.name,
                    positional.len()
                ),
            ))
        }
    };
    let needs_fan_in = || {
        Diagnostic::new(name.span, format!("'{}' needs fan_in for a {ty}", name.name))
            .with_hint(format!("write {}(fan_in: 64, seed: 1)", name.name))
    };
    Ok(match name.name.as_str() {
        "uniform" => {
            expect(2)?;
            Initializer::Uniform(positional[0], positional[1])
        }
        "normal" => {
            expect(2)?;
            Initializer::Normal(positional[0], positional[1])
        }
        "xavier" => {
            expect(0)?;
            let Some(fan_out) = fan_out else {
                return Err(Diagnostic::new(name.span, "'xavier' initializes a matrix")
                    .with_hint("for a bias use linear_init(fan_in: N) or a constant"));
            };
            let bound = (6.0 / (fan_in + fan_out)).sqrt();
            Initializer::Uniform(-bound, bound)
        }
        _ => {
            expect(0)?;
            if fan_in.is_nan() {
                return Err(needs_fan_in());
            }
            // kaiming: He uniform for ReLU; linear_init: PyTorch's default for nn.Linear.
            let bound = if name.name == "kaiming" {
                (6.0 / fan_in).sqrt()
            } else {
                1.0 / fan_in.sqrt()
            };
            Initializer::Uniform(-bound, bound)
        }
    })
}

/// Each layer of an mlp param: its matrix from the initializer with the layer's fan-in and fan-out;
/// its bias as PyTorch's `nn.Linear` does for `linear_init` (uniform ±1/√fan_in), zero for `xavier` and
/// `kaiming`, and from the distribution for `uniform` and `normal`. Layer l draws from seed·1000 + 2l
/// (matrix) and + 2l + 1 (bias).
fn mlp_init(
    shape: &crate::types::MlpShape,
    name: &Ident,
    positional: &[f64],
    seed: u64,
) -> Result<Vec<f32>, Diagnostic> {
    let ty = Type::Mlp(shape.clone());
    let mut values = Vec::with_capacity(ty.scalars());
    for (l, (rows, cols)) in shape.layers().into_iter().enumerate() {
        let layer_seed = seed.wrapping_mul(1000).wrapping_add(2 * l as u64);
        let weights = initializer(name, positional, cols as f64, Some(rows as f64), &ty)?;
        values.extend(weights.sample(rows * cols, layer_seed));
        match name.name.as_str() {
            "xavier" | "kaiming" => values.extend(std::iter::repeat_n(0.0, rows)),
            "linear_init" => {
                let bound = 1.0 / (cols as f64).sqrt();
                values.extend(Initializer::Uniform(-bound, bound).sample(rows, layer_seed + 1));
            }
            _ => values.extend(weights.sample(rows, layer_seed + 1)),
        }
    }
    Ok(values)
}
