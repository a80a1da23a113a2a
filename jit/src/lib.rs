//! Cranelift code generation for nerfjit: IR graphs to native kernels that evaluate 4 points per f32x4
//! vector, in structure-of-arrays buffers, with host features (SSE4.1, AVX, FMA) from `cranelift-native`.
//!
//! Every Cranelift call of the project lives in this crate. A [`Kernel`] is compiled from any
//! [`nerfjit_dsl::ir::Graph`]; the kernel kinds (value, gradient, vector-Jacobian product, second order)
//! differ only in the graph, built by [`nerfjit_dsl::kernel_graphs`].
//!
//! ```
//! use nerfjit_dsl::{compile, kernel_graphs};
//! let program = compile("s.sdf", "fn sdf(p: vec3) -> f32 = length(p) - 1.0").unwrap();
//! let f = program.lower("sdf").unwrap();
//! let k = nerfjit_jit::Kernel::compile(&kernel_graphs::value(&f), Default::default()).unwrap();
//! let (x, y, z) = ([2.0f32, 0.0], [0.0f32, 0.5], [0.0f32, 0.0]);
//! let mut d = [0.0f32; 2];
//! k.eval(2, &[&x, &y, &z], &mut [&mut d], &[], &mut []);
//! assert_eq!(d, [1.0, -0.5]);
//! ```

// The dense products (f32 with AVX-512/AVX2, bfloat16 on AMX or AVX-512 BF16) and the grid encodings' reads and scatters
// are public only with the `bench` feature, for the benchmark workloads of `nerfjit-bench` that time them
// alone.
#[cfg(feature = "bench")]
pub mod bf16;
#[cfg(not(feature = "bench"))]
mod bf16;
mod cache;
mod codegen;
#[cfg(feature = "bench")]
pub mod gemm;
#[cfg(not(feature = "bench"))]
mod gemm;
#[cfg(feature = "bench")]
pub mod grid_encoding;
#[cfg(not(feature = "bench"))]
mod grid_encoding;
mod kernel;
mod marcher;
pub mod profile;
mod simd;
mod tape;

pub use bf16::Precision;
pub use cache::KernelCache;
pub use kernel::{CompileStats, HeldScatters, JitError, Kernel, Options, Passes, MAX_KERNEL_NODES};
pub use marcher::{Marcher, Stop};
pub use nerfjit_dsl::march_rays::MarchRays;
pub use tape::{fused_products, Tape};
