//! Lowered values: the scalar IR values that make up a value of the language.

use crate::ir::V;
use crate::types::Type;

/// A value of the language during lowering, as IR values per scalar component.
#[derive(Clone, Debug, PartialEq)]
pub enum Val {
    /// An f32.
    Scalar(V),
    /// A vector, one IR value per component.
    Vector(Vec<V>),
    /// A matrix param (row-major, starting at param index `offset`).
    Matrix {
        /// Index of the first element in the param vector.
        offset: u32,
        /// Rows.
        rows: usize,
        /// Columns.
        cols: usize,
    },
    /// An `mlp` param (layers' matrices and biases in order, starting at param index `offset`).
    Mlp {
        /// Index of the first element in the param vector.
        offset: u32,
        /// The layers.
        shape: crate::types::MlpShape,
    },
    /// A grid encoding's table (starting at param index `offset`).
    Grid {
        /// Index of the first element in the param vector.
        offset: u32,
        /// The grid's layout.
        shape: crate::types::GridShape,
    },
    /// Several values.
    Tuple(Vec<Val>),
}

impl Val {
    /// The language type of this value.
    pub fn ty(&self) -> Type {
        match self {
            Val::Scalar(_) => Type::F32,
            Val::Vector(v) => Type::Vec(v.len()),
            Val::Matrix { rows, cols, .. } => Type::Mat(*rows, *cols),
            Val::Mlp { shape, .. } => Type::Mlp(shape.clone()),
            Val::Grid { shape, .. } => Type::Grid(shape.clone()),
            Val::Tuple(vs) => Type::Tuple(vs.iter().map(Val::ty).collect()),
        }
    }

    /// The components of a scalar or vector (None for matrices and tuples).
    pub fn components(&self) -> Option<Vec<V>> {
        match self {
            Val::Scalar(v) => Some(vec![*v]),
            Val::Vector(vs) => Some(vs.clone()),
            _ => None,
        }
    }

    /// All scalar IR values of a value, flattened in order (matrices are not flattened: None).
    pub fn flatten(&self) -> Option<Vec<V>> {
        match self {
            Val::Tuple(vs) => {
                let mut out = Vec::new();
                for v in vs {
                    out.extend(v.flatten()?);
                }
                Some(out)
            }
            Val::Matrix { .. } | Val::Mlp { .. } | Val::Grid { .. } => None,
            _ => self.components(),
        }
    }

    /// Converts `self` to type `target` where [`Type::coerces_to`] allows it.
    pub fn coerce(self, target: &Type) -> Val {
        match (self, target) {
            (Val::Vector(v), Type::F32) if v.len() == 1 => Val::Scalar(v[0]),
            (Val::Scalar(s), Type::Vec(1)) => Val::Vector(vec![s]),
            (Val::Tuple(vs), Type::Tuple(ts)) if vs.len() == ts.len() => {
                Val::Tuple(vs.into_iter().zip(ts).map(|(v, t)| v.coerce(t)).collect())
            }
            (v, _) => v,
        }
    }

    /// Builds a value of type `ty` from flat scalar values (the inverse of [`Val::flatten`]).
    pub fn unflatten(ty: &Type, scalars: &mut impl Iterator<Item = V>) -> Val {
        match ty {
            Type::F32 => Val::Scalar(scalars.next().expect("enough scalars")),
            Type::Vec(n) => Val::Vector(scalars.take(*n).collect()),
            Type::Tuple(ts) => Val::Tuple(ts.iter().map(|t| Val::unflatten(t, scalars)).collect()),
            Type::Mat(..) | Type::Mlp(_) | Type::Grid(_) => {
                unreachable!("matrices are never function inputs")
            }
        }
    }
}
