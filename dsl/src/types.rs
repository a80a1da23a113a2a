//! The types of the language.

use std::fmt;

/// A value's type. Vectors of any length share one representation: `vec3` is `Vec(3)`.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum Type {
    /// A scalar.
    F32,
    /// A vector of n scalars (`vec2`, `vec3`, `vec4`, `vec<n>`).
    Vec(usize),
    /// A matrix of rows × columns (params only), used by `dense`.
    Mat(usize, usize),
    /// The weights and biases of a ReLU network (params only), used by `mlp`.
    Mlp(MlpShape),
    /// The table of a grid encoding (params only), read by `hashgrid` or `grid`.
    Grid(GridShape),
    /// Several results of a function.
    Tuple(Vec<Type>),
}

/// The shape of a `hashgrid<3, levels: L, features: F, log2_size: T, base: N0, finest: N1, bounds: B>` or
/// `grid<3, res: R, features: F, bounds: B>` param (a dense grid is one level of R − 1 cells per axis, never
/// hashed). See [`crate::grid`] for the layout.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct GridShape {
    /// Whether the param was declared as a `hashgrid` (else a dense `grid`).
    pub hashed: bool,
    /// The layout, with its table at param 0.
    pub layout: crate::ir::GridSpec,
}

impl GridShape {
    /// The IR's description of this grid with its table at param `table`.
    pub fn spec(&self, table: u32) -> crate::ir::GridSpec {
        crate::ir::GridSpec { table, ..self.layout }
    }
}

/// The shape of an `mlp<input, width, depth, skip: k>` param: `depth` layers of `width` outputs; layer 0
/// reads the `input`-wide vector, the others the previous layer's output, and layer k (if any) that
/// output joined with the input again (a skip connection).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct MlpShape {
    /// Width of the network's input.
    pub input: usize,
    /// Outputs of every layer.
    pub width: usize,
    /// Layers.
    pub depth: usize,
    /// The layer whose input is joined with the network's input.
    pub skip: Option<usize>,
}

impl MlpShape {
    /// (rows, columns) of each layer's weight matrix, in order. In the param block, each layer's
    /// row-major matrix is followed by its bias.
    pub fn layers(&self) -> Vec<(usize, usize)> {
        (0..self.depth)
            .map(|l| {
                let previous = if l == 0 { self.input } else { self.width };
                let joined = if self.skip == Some(l) { self.input } else { 0 };
                (self.width, previous + joined)
            })
            .collect()
    }
}

impl Type {
    /// How many scalars a value of this type holds.
    pub fn scalars(&self) -> usize {
        match self {
            Type::F32 => 1,
            Type::Vec(n) => *n,
            Type::Mat(r, c) => r * c,
            Type::Mlp(shape) => shape.layers().iter().map(|(r, c)| r * c + r).sum(),
            Type::Grid(shape) => shape.layout.n_params() as usize,
            Type::Tuple(ts) => ts.iter().map(Type::scalars).sum(),
        }
    }

    /// Whether a value of type `self` may stand where `target` is expected (`vec<1>` passes as f32).
    pub fn coerces_to(&self, target: &Type) -> bool {
        self == target
            || matches!(
                (self, target),
                (Type::Vec(1), Type::F32) | (Type::F32, Type::Vec(1))
            )
            || match (self, target) {
                (Type::Tuple(a), Type::Tuple(b)) => {
                    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.coerces_to(y))
                }
                _ => false,
            }
    }
}

impl fmt::Display for Type {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Type::F32 => write!(f, "f32"),
            Type::Vec(n @ 2..=4) => write!(f, "vec{n}"),
            Type::Vec(n) => write!(f, "vec<{n}>"),
            Type::Mat(r, c) => write!(f, "mat<{r}, {c}>"),
            Type::Mlp(s) => match s.skip {
                Some(k) => write!(f, "mlp<{}, {}, {}, skip: {k}>", s.input, s.width, s.depth),
                None => write!(f, "mlp<{}, {}, {}>", s.input, s.width, s.depth),
            },
            Type::Grid(GridShape { hashed, layout: g }) => {
                let extent = f32::from_bits(g.extent);
                if *hashed {
                    write!(
                        f,
                        "hashgrid<3, levels: {}, features: {}, log2_size: {}, base: {}, finest: {}, bounds: {extent}>",
                        g.levels, g.features, g.log2_size, g.base, g.finest
                    )
                } else {
                    write!(
                        f,
                        "grid<3, res: {}, features: {}, bounds: {extent}>",
                        g.base + 1,
                        g.features
                    )
                }
            }
            Type::Tuple(ts) => {
                write!(f, "(")?;
                for (i, t) in ts.iter().enumerate() {
                    if i > 0 {
                        write!(f, ", ")?;
                    }
                    write!(f, "{t}")?;
                }
                write!(f, ")")
            }
        }
    }
}
