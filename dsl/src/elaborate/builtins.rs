//! The builtin functions: their names, signatures and lowering to scalar IR.

use crate::ast::Ident;
use crate::diag::{Diagnostic, Span};
use crate::elaborate::{EResult, Elaborator};
use crate::ir::{Graph, Op, V};
use crate::value::Val;

/// Every builtin, with the signature shown in hints. `T` is f32 or any vector, applied componentwise.
const SIGNATURES: &[(&str, &str)] = &[
    ("neg", "neg(x: T) -> T"),
    ("sin", "sin(x: T) -> T"),
    ("cos", "cos(x: T) -> T"),
    ("tan", "tan(x: T) -> T"),
    ("exp", "exp(x: T) -> T"),
    ("log", "log(x: T) -> T"),
    ("sqrt", "sqrt(x: T) -> T"),
    ("abs", "abs(x: T) -> T"),
    ("sign", "sign(x: T) -> T"),
    ("floor", "floor(x: T) -> T"),
    ("fract", "fract(x: T) -> T"),
    ("round", "round(x: T) -> T"),
    ("relu", "relu(x: T) -> T"),
    ("sigmoid", "sigmoid(x: T) -> T"),
    ("softplus", "softplus(x: T) -> T"),
    ("trunc_exp", "trunc_exp(x: T) -> T"),
    ("tanh", "tanh(x: T) -> T"),
    ("min", "min(a: T, b: T) -> T"),
    ("max", "max(a: T, b: T) -> T"),
    ("pow", "pow(x: T, y: T) -> T"),
    ("mod", "mod(x: T, y: T) -> T"),
    ("step", "step(edge: T, x: T) -> T"),
    ("clamp", "clamp(x: T, lo: T, hi: T) -> T"),
    ("mix", "mix(a: T, b: T, t: T) -> T"),
    ("smoothstep", "smoothstep(e0: T, e1: T, x: T) -> T"),
    ("select", "select(c: T, a: T, b: T) -> T"),
    ("length", "length(v: vecN) -> f32"),
    ("dot", "dot(a: vecN, b: vecN) -> f32"),
    ("cross", "cross(a: vec3, b: vec3) -> vec3"),
    ("normalize", "normalize(v: vecN) -> vecN"),
    ("sum", "sum(v: vecN) -> f32"),
    ("concat", "concat(a, b, ...) -> vec<total>"),
    ("harmonic", "harmonic(x: vec<k>, n) -> vec<k + 2kn>"),
    ("dense", "dense(w: mat<R, C>, b: vec<R>, x: vec<C>) -> vec<R>"),
    ("mlp", "mlp(net: mlp<I, W, D>, x: vec<I>) -> vec<W>"),
    (
        "hashgrid",
        "hashgrid(g: hashgrid<3, ...>, p: vec3) -> vec<levels·features>",
    ),
    ("grid", "grid(v: grid<3, ...>, p: vec3) -> vec<features>"),
    ("sh", "sh(d: vec3, degree: 1..4) -> vec<degree²>"),
    ("vec2", "vec2(x, y) or vec2(s) -> vec2"),
    ("vec3", "vec3(x, y, z) or vec3(s) -> vec3"),
    ("vec4", "vec4(x, y, z, w) or vec4(s) -> vec4"),
];

/// The names of all builtins.
pub const NAMES: &[&str] = &[
    "neg",
    "sin",
    "cos",
    "tan",
    "exp",
    "log",
    "sqrt",
    "abs",
    "sign",
    "floor",
    "fract",
    "round",
    "relu",
    "sigmoid",
    "softplus",
    "trunc_exp",
    "tanh",
    "min",
    "max",
    "pow",
    "mod",
    "step",
    "clamp",
    "mix",
    "smoothstep",
    "select",
    "length",
    "dot",
    "cross",
    "normalize",
    "sum",
    "concat",
    "harmonic",
    "dense",
    "mlp",
    "hashgrid",
    "grid",
    "sh",
    "vec2",
    "vec3",
    "vec4",
];

/// Param initializers, valid only as the initial value of a `param`.
pub const INITIALIZERS: &[&str] = &["uniform", "normal", "xavier", "kaiming", "linear_init"];

/// Whether `name` is a builtin function.
pub fn is_builtin(name: &str) -> bool {
    NAMES.contains(&name)
}

/// Whether `name` is a param initializer.
pub fn is_initializer(name: &str) -> bool {
    INITIALIZERS.contains(&name)
}

/// The signature of a builtin, for hints.
pub fn signature(name: &str) -> &'static str {
    SIGNATURES.iter().find(|(n, _)| *n == name).map_or("", |(_, s)| s)
}

fn arity_error(name: &Ident, expected: &str, got: usize) -> Diagnostic {
    Diagnostic::new(
        name.span,
        format!(
            "wrong number of arguments: '{}' takes {expected}, got {got}",
            name.name
        ),
    )
    .with_hint(format!("write {}", signature(&name.name)))
}

fn unary(g: &mut Graph, name: &str, x: V) -> V {
    let zero = g.constant(0.0);
    match name {
        "neg" => g.push(Op::Neg(x)),
        "sin" => g.push(Op::Sin(x)),
        "cos" => g.push(Op::Cos(x)),
        "tan" => g.push(Op::Tan(x)),
        "exp" => g.push(Op::Exp(x)),
        "log" => g.push(Op::Log(x)),
        "sqrt" => g.push(Op::Sqrt(x)),
        "abs" => g.push(Op::Abs(x)),
        "sign" => g.push(Op::Sign(x)),
        "floor" => g.push(Op::Floor(x)),
        "fract" => {
            let f = g.push(Op::Floor(x));
            g.push(Op::Sub(x, f))
        }
        "round" => {
            let half = g.constant(0.5);
            let s = g.push(Op::Add(x, half));
            g.push(Op::Floor(s))
        }
        "relu" => g.push(Op::Max(x, zero)),
        "sigmoid" => g.push(Op::Sigmoid(x)),
        "softplus" => g.push(Op::Softplus(x)),
        "trunc_exp" => g.push(Op::TruncExp(x)),
        "tanh" => g.push(Op::Tanh(x)),
        _ => unreachable!("not a unary builtin: {name}"),
    }
}

/// `x^y`, with small integer and half powers of a constant exponent lowered to products and roots.
pub fn pow(g: &mut Graph, x: V, y: V) -> V {
    match g.const_value(y) {
        Some(0.5) => g.push(Op::Sqrt(x)),
        Some(e) if e.fract() == 0.0 && e.abs() <= 16.0 => {
            let one = g.constant(1.0);
            let mut result = one;
            let mut base = x;
            let mut n = e.abs() as u32;
            while n > 0 {
                if n & 1 == 1 {
                    result = g.push(Op::Mul(result, base));
                }
                n >>= 1;
                if n > 0 {
                    base = g.push(Op::Mul(base, base));
                }
            }
            if e < 0.0 {
                g.push(Op::Div(one, result))
            } else {
                result
            }
        }
        _ => {
            let l = g.push(Op::Log(x));
            let t = g.push(Op::Mul(y, l));
            g.push(Op::Exp(t))
        }
    }
}

fn nary(g: &mut Graph, name: &str, a: &[V]) -> V {
    match name {
        "min" => g.push(Op::Min(a[0], a[1])),
        "max" => g.push(Op::Max(a[0], a[1])),
        "pow" => pow(g, a[0], a[1]),
        "mod" => {
            let q = g.push(Op::Div(a[0], a[1]));
            let f = g.push(Op::Floor(q));
            let m = g.push(Op::Mul(a[1], f));
            g.push(Op::Sub(a[0], m))
        }
        "step" => g.push(Op::Le(a[0], a[1])),
        "clamp" => {
            let lo = g.push(Op::Max(a[0], a[1]));
            g.push(Op::Min(lo, a[2]))
        }
        "mix" => {
            let d = g.push(Op::Sub(a[1], a[0]));
            let t = g.push(Op::Mul(d, a[2]));
            g.push(Op::Add(a[0], t))
        }
        "smoothstep" => {
            let (zero, one) = (g.constant(0.0), g.constant(1.0));
            let num = g.push(Op::Sub(a[2], a[0]));
            let den = g.push(Op::Sub(a[1], a[0]));
            let q = g.push(Op::Div(num, den));
            let lo = g.push(Op::Max(q, zero));
            let t = g.push(Op::Min(lo, one));
            let (two, three) = (g.constant(2.0), g.constant(3.0));
            let tt = g.push(Op::Mul(t, t));
            let two_t = g.push(Op::Mul(two, t));
            let w = g.push(Op::Sub(three, two_t));
            g.push(Op::Mul(tt, w))
        }
        "select" => g.push(Op::Select(a[0], a[1], a[2])),
        _ => unreachable!("not an n-ary builtin: {name}"),
    }
}

/// Lowers a call of builtin `name` on already lowered arguments.
pub fn call(el: &mut Elaborator, name: &Ident, args: Vec<(Val, Span)>, span: Span) -> EResult<Val> {
    let n = args.len();
    let want = |k: usize| {
        if n == k {
            Ok(())
        } else {
            Err(arity_error(name, &k.to_string(), n))
        }
    };
    let nm = name.name.as_str();
    match nm {
        "neg" | "sin" | "cos" | "tan" | "exp" | "log" | "sqrt" | "abs" | "sign" | "floor" | "fract"
        | "round" | "relu" | "sigmoid" | "softplus" | "trunc_exp" | "tanh" => {
            want(1)?;
            let (v, at) = args.into_iter().next().expect("one argument");
            el.map1(v, at, nm, |g, x| unary(g, nm, x))
        }
        "min" | "max" | "pow" | "mod" | "step" => {
            want(2)?;
            let vals: Vec<Val> = args.into_iter().map(|a| a.0).collect();
            el.map_n(&vals, span, nm, |g, a| nary(g, nm, a))
        }
        "clamp" | "mix" | "smoothstep" | "select" => {
            want(3)?;
            let vals: Vec<Val> = args.into_iter().map(|a| a.0).collect();
            el.map_n(&vals, span, nm, |g, a| nary(g, nm, a))
        }
        "length" | "sum" | "normalize" => {
            want(1)?;
            let comps = el.vector(&args[0].0, args[0].1)?;
            let g = &mut *el.g;
            Ok(match nm {
                "sum" => {
                    let mut acc = g.constant(0.0);
                    for &c in &comps {
                        acc = g.push(Op::Add(acc, c));
                    }
                    Val::Scalar(acc)
                }
                "length" => Val::Scalar(g.length(&comps)),
                _ => {
                    let len = g.length(&comps);
                    Val::Vector(comps.iter().map(|&c| g.push(Op::Div(c, len))).collect())
                }
            })
        }
        "dot" | "cross" => {
            want(2)?;
            let a = el.vector(&args[0].0, args[0].1)?;
            let b = el.vector(&args[1].0, args[1].1)?;
            let needed = if nm == "cross" { Some(3) } else { None };
            if a.len() != b.len() || needed.is_some_and(|k| a.len() != k) {
                return Err(Diagnostic::new(
                    span,
                    format!(
                        "mismatched types for '{nm}': {} and {}",
                        args[0].0.ty(),
                        args[1].0.ty()
                    ),
                )
                .with_hint(format!("write {}", signature(nm))));
            }
            let g = &mut *el.g;
            if nm == "dot" {
                return Ok(Val::Scalar(g.dot(&a, &b)));
            }
            let mut term = |i: usize, j: usize| {
                let p = g.push(Op::Mul(a[i], b[j]));
                let q = g.push(Op::Mul(a[j], b[i]));
                g.push(Op::Sub(p, q))
            };
            Ok(Val::Vector(vec![term(1, 2), term(2, 0), term(0, 1)]))
        }
        "concat" | "vec2" | "vec3" | "vec4" => {
            if n == 0 {
                return Err(arity_error(name, "at least 1", 0));
            }
            let mut comps = Vec::new();
            for (v, at) in &args {
                comps.extend(el.vector(v, *at)?);
            }
            if let Some(k) = nm.strip_prefix("vec").and_then(|k| k.parse::<usize>().ok()) {
                if comps.len() == 1 {
                    comps = vec![comps[0]; k];
                } else if comps.len() != k {
                    return Err(Diagnostic::new(
                        span,
                        format!("'{nm}' needs {k} components or 1 to repeat, got {}", comps.len()),
                    )
                    .with_hint(format!("write {}", signature(nm))));
                }
            }
            Ok(Val::Vector(comps))
        }
        "harmonic" => harmonic(el, name, args),
        "dense" => dense(el, name, args),
        "mlp" => mlp(el, name, args),
        "hashgrid" | "grid" => grid(el, name, args),
        "sh" => spherical_harmonics(el, name, args),
        _ => unreachable!("unhandled builtin {nm}"),
    }
}

/// `harmonic(x, n)`: [x, sin(2⁰x), …, sin(2ⁿ⁻¹x), cos(2⁰x), …, cos(2ⁿ⁻¹x)] with the sines (and cosines)
/// ordered component-major, as PyTorch3D's `HarmonicEmbedding(n, include_input=True)` up to order.
fn harmonic(el: &mut Elaborator, name: &Ident, args: Vec<(Val, Span)>) -> EResult<Val> {
    if args.len() != 2 {
        return Err(arity_error(name, "2", args.len()));
    }
    let comps = el.vector(&args[0].0, args[0].1)?;
    let n = match &args[1].0 {
        Val::Scalar(v) => el.g.const_value(*v),
        _ => None,
    };
    let n = match n {
        Some(k) if k.fract() == 0.0 && (0.0..=24.0).contains(&k) => k as u32,
        _ => {
            return Err(Diagnostic::new(
                args[1].1,
                "the number of frequencies must be a constant from 0 to 24",
            )
            .with_hint("write e.g. harmonic(p, 6)"))
        }
    };
    let g = &mut *el.g;
    let mut scaled = Vec::new();
    for &c in &comps {
        for k in 0..n {
            let f = g.constant(f64::from(1u32 << k));
            scaled.push(g.push(Op::Mul(c, f)));
        }
    }
    let mut out = comps.clone();
    out.extend(scaled.iter().map(|&s| g.push(Op::Sin(s))));
    out.extend(scaled.iter().map(|&s| g.push(Op::Cos(s))));
    Ok(Val::Vector(out))
}

/// `hashgrid(g, p)` / `grid(v, p)`: the trilinear read of every level of a grid encoding at p (see
/// [`crate::grid`]), levels × features values, level-major.
fn grid(el: &mut Elaborator, name: &Ident, args: Vec<(Val, Span)>) -> EResult<Val> {
    if args.len() != 2 {
        return Err(arity_error(name, "2", args.len()));
    }
    let hashed = name.name == "hashgrid";
    let shape = match &args[0].0 {
        Val::Grid { offset, shape } if shape.hashed == hashed => shape.spec(*offset),
        other => {
            let (kind, example) = if hashed {
                (
                    "hashgrid",
                    "'param g: hashgrid<3, levels: 16, features: 2> = uniform(-1e-4, 1e-4)'",
                )
            } else {
                ("grid", "'param v: grid<3, res: 128, features: 4> = 0'")
            };
            let found = other.ty();
            let mut d = Diagnostic::new(
                args[0].1,
                format!("'{kind}' needs a {kind} param first, found {found}"),
            );
            d = match found {
                crate::types::Type::Grid(_) => {
                    d.with_hint(format!("read a {found} with {}", found_reader(hashed)))
                }
                _ => d.with_hint(format!("declare one with {example}")),
            };
            return Err(d);
        }
    };
    let p = el.vector(&args[1].0, args[1].1)?;
    let [x, y, z] = p[..] else {
        return Err(Diagnostic::new(
            args[1].1,
            format!("'{}' reads a vec3, found {}", name.name, args[1].0.ty()),
        ));
    };
    Ok(Val::Vector(el.g.grid(shape, [x, y, z], 0)))
}

/// The builtin that reads the other kind of grid.
fn found_reader(hashed: bool) -> &'static str {
    if hashed {
        "grid(v, p)"
    } else {
        "hashgrid(g, p)"
    }
}

/// `sh(d, degree)`: the real spherical harmonics of direction d in bands 0..degree (degree² values, the
/// basis and signs of instant-ngp's direction encoding), as polynomials of d's components.
fn spherical_harmonics(el: &mut Elaborator, name: &Ident, args: Vec<(Val, Span)>) -> EResult<Val> {
    if args.len() != 2 {
        return Err(arity_error(name, "2", args.len()));
    }
    let d = el.vector(&args[0].0, args[0].1)?;
    let [x, y, z] = d[..] else {
        return Err(Diagnostic::new(
            args[0].1,
            format!("'sh' reads a direction vec3, found {}", args[0].0.ty()),
        ));
    };
    let degree = match &args[1].0 {
        Val::Scalar(v) => el.g.const_value(*v),
        _ => None,
    };
    let degree = match degree {
        Some(k) if k.fract() == 0.0 && (1.0..=4.0).contains(&k) => k as usize,
        _ => {
            return Err(
                Diagnostic::new(args[1].1, "the degree must be a constant from 1 to 4")
                    .with_hint("sh(d, 4) gives 16 values"),
            )
        }
    };
    let g = &mut *el.g;
    // Σ cᵢ·(monomial) terms: each basis function is a list of (coefficient, powers of x, y, z).
    type Term = (f64, [u32; 3]);
    const BASIS: [&[Term]; 16] = [
        &[(0.28209479177387814, [0, 0, 0])],
        &[(-0.48860251190291987, [0, 1, 0])],
        &[(0.48860251190291987, [0, 0, 1])],
        &[(-0.48860251190291987, [1, 0, 0])],
        &[(1.0925484305920792, [1, 1, 0])],
        &[(-1.0925484305920792, [0, 1, 1])],
        &[(0.94617469575756, [0, 0, 2]), (-0.31539156525252, [0, 0, 0])],
        &[(-1.0925484305920792, [1, 0, 1])],
        &[(0.5462742152960396, [2, 0, 0]), (-0.5462742152960396, [0, 2, 0])],
        &[(-1.7701307697799307, [2, 1, 0]), (0.5900435899266435, [0, 3, 0])],
        &[(2.890611442640554, [1, 1, 1])],
        &[(0.4570457994644657, [0, 1, 0]), (-2.2852289973223288, [0, 1, 2])],
        &[(1.865881662950577, [0, 0, 3]), (-1.1195289977703462, [0, 0, 1])],
        &[(0.4570457994644657, [1, 0, 0]), (-2.2852289973223288, [1, 0, 2])],
        &[(1.445305721320277, [2, 0, 1]), (-1.445305721320277, [0, 2, 1])],
        &[(-0.5900435899266435, [3, 0, 0]), (1.7701307697799307, [1, 2, 0])],
    ];
    let power = |g: &mut Graph, v: V, k: u32| -> V {
        let mut acc = g.constant(1.0);
        for _ in 0..k {
            acc = g.push(Op::Mul(acc, v));
        }
        acc
    };
    let mut out = Vec::with_capacity(degree * degree);
    for terms in &BASIS[..degree * degree] {
        let mut sum = g.constant(0.0);
        for &(c, [a, b, e]) in terms.iter() {
            let (px, py, pz) = (power(g, x, a), power(g, y, b), power(g, z, e));
            let xy = g.push(Op::Mul(px, py));
            let monomial = g.push(Op::Mul(xy, pz));
            let c = g.constant(c);
            let term = g.push(Op::Mul(c, monomial));
            sum = g.push(Op::Add(sum, term));
        }
        out.push(sum);
    }
    Ok(Val::Vector(out))
}

/// `mlp(net, x)`: the ReLU layers of an `mlp<I, W, D>` param applied to x (each layer relu(W·h + b); the
/// skip layer reads its predecessor's output joined with x).
fn mlp(el: &mut Elaborator, name: &Ident, args: Vec<(Val, Span)>) -> EResult<Val> {
    if args.len() != 2 {
        return Err(arity_error(name, "2", args.len()));
    }
    let Val::Mlp { offset, ref shape } = args[0].0 else {
        return Err(Diagnostic::new(
            args[0].1,
            format!("'mlp' needs an mlp param first, found {}", args[0].0.ty()),
        )
        .with_hint("declare one with 'param net: mlp<39, 128, 6, skip: 3> = linear_init(seed: 1)'"));
    };
    let x = el.vector(&args[1].0, args[1].1)?;
    if x.len() != shape.input {
        return Err(Diagnostic::new(
            args[1].1,
            format!(
                "'mlp' with a {} needs vec<{}>, found {}",
                args[0].0.ty(),
                shape.input,
                args[1].0.ty()
            ),
        ));
    }
    let g = &mut *el.g;
    let mut h = x.clone();
    let mut at = offset;
    for (l, (rows, cols)) in shape.layers().into_iter().enumerate() {
        let input: Vec<V> = if shape.skip == Some(l) {
            h.iter().chain(&x).copied().collect()
        } else {
            h
        };
        let product = g.dense(at, rows as u32, cols as u32, false, &input);
        let bias = at + (rows * cols) as u32;
        h = product
            .iter()
            .enumerate()
            .map(|(r, &p)| {
                let b = g.param(bias + r as u32);
                let z = g.push(Op::Add(p, b));
                unary(g, "relu", z)
            })
            .collect();
        at = bias + rows as u32;
    }
    Ok(Val::Vector(h))
}

/// `dense(w, b, x)` = w·x + b and `dense(w, x)` = w·x, for a matrix param w.
fn dense(el: &mut Elaborator, name: &Ident, args: Vec<(Val, Span)>) -> EResult<Val> {
    if !(2..=3).contains(&args.len()) {
        return Err(arity_error(name, "2 or 3", args.len()));
    }
    let Val::Matrix { offset, rows, cols } = args[0].0 else {
        return Err(Diagnostic::new(
            args[0].1,
            format!("'dense' needs a matrix param first, found {}", args[0].0.ty()),
        )
        .with_hint("declare one with 'param w: mat<R, C> = xavier(seed: 1)'"));
    };
    let (x_val, x_span) = &args[args.len() - 1];
    let x = el.vector(x_val, *x_span)?;
    if x.len() != cols {
        return Err(Diagnostic::new(
            *x_span,
            format!(
                "'dense' with a mat<{rows}, {cols}> needs vec<{cols}>, found {}",
                x_val.ty()
            ),
        ));
    }
    let bias = if args.len() == 3 {
        let b = el.vector(&args[1].0, args[1].1)?;
        if b.len() != rows {
            return Err(Diagnostic::new(
                args[1].1,
                format!(
                    "'dense' with a mat<{rows}, {cols}> needs a bias vec<{rows}>, found {}",
                    args[1].0.ty()
                ),
            ));
        }
        Some(b)
    } else {
        None
    };
    let g = &mut *el.g;
    let product = g.dense(offset, rows as u32, cols as u32, false, &x);
    let out = match bias {
        Some(b) => product
            .iter()
            .zip(b)
            .map(|(&p, b)| g.push(Op::Add(p, b)))
            .collect(),
        None => product,
    };
    Ok(Val::Vector(out))
}
