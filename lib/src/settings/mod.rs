//! The settings of blocks: the schema of every setting of every block kind, typed access to one block's
//! settings, the typed structs plans read them into, and the parsers of their values (primitives, composite
//! values, cameras).

pub mod block;
pub mod camera;
pub mod primitives;
pub mod schema;
pub mod typed;
pub mod values;
