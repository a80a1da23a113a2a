//! What the script fuzzers skip: programs with networks too large to differentiate quickly under the
//! sanitizer (a course-size network's gradient takes seconds there, beyond libFuzzer's timeout, and
//! exercises nothing a small one does not).

use nerfjit_dsl::{Program, Type};

/// Most weights (params outside grid tables) of a program whose functions the fuzzers lower.
const MAX_DENSE_PARAMS: usize = 20_000;

/// Whether `program`'s params outside grid encodings' tables are few enough to lower and compile.
pub fn small_enough(program: &Program) -> bool {
    let grid = |ty: &Type| matches!(ty, Type::Grid(_));
    let dense: usize = program
        .params
        .iter()
        .filter(|p| !grid(&p.ty))
        .map(|p| p.ty.scalars())
        .sum();
    dense <= MAX_DENSE_PARAMS
}
