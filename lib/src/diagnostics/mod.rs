//! What nerfjit tells a user about a field beyond errors: where it is not finite, whether an SDF is
//! steeper than its sphere tracer assumes.

pub mod nonfinite;
pub mod steepness;
