//! A roofline for a training step: what this machine allows for each phase's work, measured in the same
//! sitting as the step (the machine's speed varies from day to day), and the step's phases set against it.
//!
//! The limits are the rates of the simplest loops that do a phase's kind of work on every thread at once:
//! - the products: independent fused multiply-adds in vector registers, or for bfloat16 products on AVX-512
//!   BF16, independent dot products of pairs (`vdpbf16ps`, 32 multiply-adds an instruction);
//! - the grid's reads and scatters: reads and read-modify-writes of 8-byte entries at random places of a
//!   table of each grid level's size (in L1, L2, L3 or memory); a point reads 8 corners on every level, so
//!   a corner's time is the mean over the levels of one random access's time at that level's size;
//! - the optimizer: a pass of Adam's reads and writes over arrays of the model's size.
//!
//! The elementwise code and the rest of the step (ray set-up, compositing, gradient sums) have no such
//! single limit. The random accesses are uniform over a level's table; the corners of one cell share cache
//! lines and nearby points share cells, so the grid's phases could beat these limits where their points
//! are coherent (none did in the sittings of docs/LOG.md).

use nerfjit_jit::bf16;
use nerfjit_jit::profile::{Phase, Times};
use nerfjit_jit::Precision;

/// The rates of this machine on all of the pool's threads.
#[derive(Clone, Debug)]
pub struct Rates {
    /// Fused multiply-adds in the widest vectors the CPU has, in FLOP/s (a multiply-add is two).
    pub fma: f64,
    /// The vector width of [`Rates::fma`] in bits.
    pub fma_bits: u32,
    /// What limits the step's products.
    pub products: ProductsRate,
    /// Per size of grid level (bytes): reads of 8-byte entries at random places of a table of that size,
    /// per second.
    pub random_reads: Vec<(usize, f64)>,
    /// Per size of grid level: read-modify-writes (`+=`) of 8-byte entries at random places, each thread
    /// in a table of its own (the step's tasks scatter into gradient accumulators of their own), per
    /// second.
    pub random_updates: Vec<(usize, f64)>,
    /// The optimizer's memory traffic (four arrays read, three written) at the model's size, in bytes
    /// per second.
    pub optimizer: f64,
    /// The bytes of each grid level's table, one entry per level.
    pub level_bytes: Vec<usize>,
}

/// The rate of the step's products.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ProductsRate {
    /// f32 products: [`Rates::fma`].
    Fma,
    /// bfloat16 products on a unit with a loop of its own here (the dot products of pairs on AVX-512
    /// BF16): its name and its rate in FLOP/s.
    Measured(&'static str, f64),
    /// bfloat16 products on a unit with no limit measured (AMX's tiles have no loop here, and rounded
    /// operands run at the FMA rate with extra work): its name.
    Unmeasured(&'static str),
}

impl Rates {
    /// Measures the rates (medians of `reps`) for grid levels of `level_bytes` each, a model of `params`
    /// floats and products in `precision`; takes a few seconds.
    pub fn measure(level_bytes: &[usize], params: usize, reps: usize, precision: Precision) -> Rates {
        let (fma, fma_bits) = fma_peak(reps);
        let products = match (precision, bf16::Unit::best()) {
            (Precision::F32, _) => ProductsRate::Fma,
            #[cfg(target_arch = "x86_64")]
            (Precision::Bf16, bf16::Unit::Avx512Bf16) => {
                ProductsRate::Measured("bf16 dot products", dot_peak(reps))
            }
            (Precision::Bf16, unit) => ProductsRate::Unmeasured(unit.name()),
        };
        let mut sizes = level_bytes.to_vec();
        sizes.sort_unstable();
        sizes.dedup();
        let random = |update| {
            sizes
                .iter()
                .map(|&bytes| (bytes, random_access(bytes, update, reps)))
                .collect()
        };
        Rates {
            fma,
            fma_bits,
            products,
            random_reads: random(false),
            random_updates: random(true),
            optimizer: optimizer_stream(params, reps),
            level_bytes: level_bytes.to_vec(),
        }
    }

    /// The better of two measurements of each rate: on a shared machine a measurement can only be slowed
    /// by others' work, so the faster one is nearer what the machine allows.
    pub fn best(self, other: &Rates) -> Rates {
        let best_of = |a: Vec<(usize, f64)>, b: &[(usize, f64)]| {
            a.into_iter()
                .zip(b)
                .map(|((bytes, x), (_, y))| (bytes, x.max(*y)))
                .collect()
        };
        Rates {
            fma: self.fma.max(other.fma),
            products: match (self.products, other.products) {
                (ProductsRate::Measured(unit, a), ProductsRate::Measured(_, b)) => {
                    ProductsRate::Measured(unit, a.max(b))
                }
                (products, _) => products,
            },
            random_reads: best_of(self.random_reads, &other.random_reads),
            random_updates: best_of(self.random_updates, &other.random_updates),
            optimizer: self.optimizer.max(other.optimizer),
            ..self
        }
    }

    /// Corner accesses per second if the corners are spread evenly over the levels: the harmonic mean of the
    /// levels' rates.
    fn corners(&self, rates: &[(usize, f64)]) -> f64 {
        let rate = |bytes| rates.iter().find(|(b, _)| *b == bytes).map_or(f64::NAN, |r| r.1);
        let seconds: f64 = self.level_bytes.iter().map(|&b| 1.0 / rate(b)).sum();
        self.level_bytes.len() as f64 / seconds
    }

    /// The rate that limits `phase`, in its [`Phase::unit`] per second (none for the elementwise code and
    /// whole steps).
    pub fn of(&self, phase: Phase) -> Option<f64> {
        match phase {
            Phase::Products | Phase::OuterProducts => match self.products {
                ProductsRate::Fma => Some(self.fma),
                ProductsRate::Measured(_, rate) => Some(rate),
                ProductsRate::Unmeasured(_) => None,
            },
            Phase::GridReads => Some(self.corners(&self.random_reads)),
            Phase::GridScatters => Some(self.corners(&self.random_updates)),
            Phase::Optimizer => Some(self.optimizer),
            Phase::Elementwise | Phase::Steps => None,
        }
    }

    /// One line naming the rates.
    pub fn describe(&self) -> String {
        let per_size = |rates: &[(usize, f64)]| {
            rates
                .iter()
                .map(|(bytes, rate)| format!("{:.0} M/s in {}", rate * 1e-6, size(*bytes)))
                .collect::<Vec<_>>()
                .join(", ")
        };
        let products = match self.products {
            ProductsRate::Fma => String::new(),
            ProductsRate::Measured(unit, rate) => format!("; {unit} {:.1} GFLOP/s", rate * 1e-9),
            ProductsRate::Unmeasured(unit) => format!("; products on {unit} (no limit measured)"),
        };
        format!(
            "machine rates on {} threads: {}-bit FMA {:.1} GFLOP/s{products}; Adam's reads and writes {:.1} GB/s; random 8-byte \
             reads {}; updates {}; so a corner {:.0} M/s read and {:.0} M/s updated over the {} levels",
            rayon::current_num_threads(),
            self.fma_bits,
            self.fma * 1e-9,
            self.optimizer * 1e-9,
            per_size(&self.random_reads),
            per_size(&self.random_updates),
            self.corners(&self.random_reads) * 1e-6,
            self.corners(&self.random_updates) * 1e-6,
            self.level_bytes.len(),
        )
    }
}

/// `bytes` in KB or MB.
fn size(bytes: usize) -> String {
    if bytes < 1 << 20 {
        format!("{:.0} KB", bytes as f64 / 1024.0)
    } else {
        format!("{:.1} MB", bytes as f64 / (1 << 20) as f64)
    }
}

/// The phases of training steps against `rates`: per phase its share of the step, its time and work per
/// sample, the time its work needs at the machine's rate, and that limit as a fraction of the time taken;
/// then the step as a whole (samples/s taken, and allowed if every limited phase ran at its limit and the
/// rest took no time). The times are summed over `threads` and divided by them, as the rates are over all
/// threads.
pub fn table(times: &Times, rates: &Rates, threads: usize) -> String {
    let samples = times.work(Phase::Steps).max(1) as f64;
    let step_ns = times.seconds(Phase::Steps) * 1e9 / samples;
    let mut out = format!(
        "  {:<17}{:>7}{:>13}{:>18}{:>14}{:>10}\n",
        "phase", "share", "ns/sample", "work/sample", "limit ns", "of limit"
    );
    let (mut accounted, mut limit_ns) = (0.0, 0.0);
    for phase in Phase::ALL.into_iter().filter(|&p| p != Phase::Steps) {
        let ns = times.seconds(phase) * 1e9 / threads as f64 / samples;
        accounted += ns;
        let work = times.work(phase) as f64 / samples;
        let limit = rates.of(phase).map(|rate| work / rate * 1e9);
        limit_ns += limit.unwrap_or(0.0);
        out += &format!(
            "  {:<17}{:>6.1}%{:>13.1}{:>18}{:>14}{:>10}\n",
            phase.name(),
            100.0 * ns / step_ns,
            ns,
            match phase.unit() {
                "" => "—".to_string(),
                unit => format!("{work:.0} {unit}"),
            },
            limit.map_or("—".to_string(), |l| format!("{l:.2}")),
            limit.map_or("—".to_string(), |l| format!("{:.1}%", 100.0 * l / ns)),
        );
    }
    let rest = step_ns - accounted;
    out += &format!(
        "  {:<17}{:>6.1}%{:>13.1}{:>18}{:>14}{:>10}\n",
        "the rest",
        100.0 * rest / step_ns,
        rest,
        "—",
        "—",
        "—"
    );
    out += &format!(
        "  step: {step_ns:.1} ns/sample = {:.3} M samples/s; the limited phases at their limits: {limit_ns:.2} ns/sample \
         = {:.2} M samples/s; the step runs at {:.1}% of that",
        1e3 / step_ns,
        1e3 / limit_ns,
        100.0 * limit_ns / step_ns
    );
    out
}

/// Runs `work` on every thread of the pool at once and returns the median wall time of `reps` runs (after
/// one to warm up).
fn on_every_thread(reps: usize, work: impl Fn(usize) + Sync) -> f64 {
    crate::time_reps(reps, || {
        rayon::broadcast(|ctx| work(ctx.index()));
    })
}

/// Iterations of the FMA chains per thread and run.
const FMA_ITERATIONS: usize = 20_000_000;

/// The FMA rate on all threads and the vector width it used.
fn fma_peak(reps: usize) -> (f64, u32) {
    let (bits, lanes_times_chains, chains) = fma_kernel();
    let threads = rayon::current_num_threads();
    let seconds = on_every_thread(reps, |_| {
        std::hint::black_box(chains(FMA_ITERATIONS));
    });
    let flops = 2.0 * (threads * FMA_ITERATIONS * lanes_times_chains) as f64;
    (flops / seconds, bits)
}

/// Iterations of the dot-product chains per thread and run.
const DOT_ITERATIONS: usize = 10_000_000;

/// The rate of AVX-512 BF16's dot products of pairs on all threads, in FLOP/s (32 multiply-adds an
/// instruction).
#[cfg(target_arch = "x86_64")]
fn dot_peak(reps: usize) -> f64 {
    let threads = rayon::current_num_threads();
    let seconds = on_every_thread(reps, |_| {
        // SAFETY: only called where bf16::Unit::best() is AVX-512 BF16, which the CPU then has.
        std::hint::black_box(unsafe { x86::dot512(DOT_ITERATIONS) });
    });
    2.0 * (threads * DOT_ITERATIONS * 16 * 32) as f64 / seconds
}

/// The widest FMA kernel this CPU runs: its vector width in bits, its lanes × chains, and the kernel, which
/// runs its iterations of independent multiply-add chains (enough of them to keep two FMA pipes of latency
/// 4 busy, and few enough to stay in the vector registers) and returns a sum so that they are kept.
fn fma_kernel() -> (u32, usize, fn(usize) -> f32) {
    #[cfg(target_arch = "x86_64")]
    {
        if is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has AVX-512F.
            return (512, 16 * 16, |n| unsafe { x86::fma512(n) });
        }
        if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has AVX2 and FMA.
            return (256, 8 * 12, |n| unsafe { x86::fma256(n) });
        }
    }
    (32, 8, fma_scalar)
}

/// [`fma_kernel`]'s chains on CPUs without vector FMAs: 8 scalar ones.
fn fma_scalar(iterations: usize) -> f32 {
    let mut acc = [1.0f32; 8];
    for _ in 0..iterations {
        for a in &mut acc {
            *a = a.mul_add(0.999_999, 1e-7);
        }
    }
    acc.iter().sum()
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    /// 16 chains of 512-bit FMAs (32 vector registers: the chains and the two operands fit).
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn fma512(iterations: usize) -> f32 {
        let (a, b) = (_mm512_set1_ps(0.999_999), _mm512_set1_ps(1e-7));
        let mut acc = [_mm512_set1_ps(1.0); 16];
        for _ in 0..iterations {
            for x in &mut acc {
                *x = _mm512_fmadd_ps(*x, a, b);
            }
        }
        let sum = acc.iter().fold(_mm512_setzero_ps(), |s, &x| _mm512_add_ps(s, x));
        _mm512_reduce_add_ps(sum)
    }

    /// 16 chains of AVX-512 BF16 dot products of pairs, as [`fma512`]'s.
    #[target_feature(enable = "avx512f,avx512bf16")]
    pub(super) unsafe fn dot512(iterations: usize) -> f32 {
        // SAFETY (both): 64 bytes of plain bits either way.
        let (a, b) = unsafe {
            (
                std::mem::transmute::<__m512, __m512bh>(_mm512_set1_ps(0.999_999)),
                std::mem::transmute::<__m512, __m512bh>(_mm512_set1_ps(1e-7)),
            )
        };
        let mut acc = [_mm512_set1_ps(1.0); 16];
        for _ in 0..iterations {
            for x in &mut acc {
                *x = _mm512_dpbf16_ps(*x, a, b);
            }
        }
        let sum = acc.iter().fold(_mm512_setzero_ps(), |s, &x| _mm512_add_ps(s, x));
        _mm512_reduce_add_ps(sum)
    }

    /// 12 chains of 256-bit FMAs (16 vector registers: 16 chains and two operands would spill).
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn fma256(iterations: usize) -> f32 {
        let (a, b) = (_mm256_set1_ps(0.999_999), _mm256_set1_ps(1e-7));
        let mut acc = [_mm256_set1_ps(1.0); 12];
        for _ in 0..iterations {
            for x in &mut acc {
                *x = _mm256_fmadd_ps(*x, a, b);
            }
        }
        let sum = acc.iter().fold(_mm256_setzero_ps(), |s, &x| _mm256_add_ps(s, x));
        let mut lanes = [0.0f32; 8];
        // SAFETY: `lanes` holds 8 floats.
        unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), sum) };
        lanes.iter().sum()
    }
}

/// Random accesses per thread and run.
const RANDOM_ACCESSES: usize = 1 << 22;

/// Random 8-byte reads (or updates, each thread in a table of its own) in tables of `bytes`, per second on
/// all threads. The indices come from a counter through a multiplicative hash, so no access waits for
/// another's value and the core overlaps as many misses as it can, as the grid's corner reads do.
fn random_access(bytes: usize, update: bool, reps: usize) -> f64 {
    let threads = rayon::current_num_threads();
    let entries = (bytes / 8).max(1);
    let shared = if update {
        Vec::new()
    } else {
        vec![[1.0f32, 2.0]; entries]
    };
    let own: Vec<std::sync::Mutex<Vec<[f32; 2]>>> = (0..if update { threads } else { 0 })
        .map(|_| std::sync::Mutex::new(vec![[1.0, 2.0]; entries]))
        .collect();
    let seconds = on_every_thread(reps, |thread| {
        let index = |i: usize| {
            let h = (i as u64 ^ (thread as u64) << 40).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            (((h >> 32) * entries as u64) >> 32) as usize
        };
        if update {
            let mut table = own[thread].lock().expect("each thread locks only its own table");
            for i in 0..RANDOM_ACCESSES {
                let e = &mut table[index(i)];
                e[0] += 1.0;
                e[1] += 1.0;
            }
            std::hint::black_box(&mut *table);
        } else {
            let mut sum = [0.0f32; 2];
            for i in 0..RANDOM_ACCESSES {
                let e = shared[index(i)];
                sum[0] += e[0];
                sum[1] += e[1];
            }
            std::hint::black_box(sum);
        }
    });
    (threads * RANDOM_ACCESSES) as f64 / seconds
}

/// Adam's memory traffic at its size: four arrays of `elements` floats (params, gradients and the two
/// moments) read and three written, with little arithmetic, over all threads; bytes read and written per
/// second (28 an element, as the optimizer's work is counted). Small tables stay in a cache, as they do
/// in training.
fn optimizer_stream(elements: usize, reps: usize) -> f64 {
    use rayon::prelude::*;
    let elements = elements.max(1 << 16);
    let (mut p, g, mut m, mut v) = (
        vec![0.0f32; elements],
        vec![1e-3f32; elements],
        vec![0.0f32; elements],
        vec![0.0f32; elements],
    );
    let chunk = elements.div_ceil(4 * rayon::current_num_threads());
    let seconds = crate::time_reps(reps, || {
        p.par_chunks_mut(chunk)
            .zip(g.par_chunks(chunk))
            .zip(m.par_chunks_mut(chunk).zip(v.par_chunks_mut(chunk)))
            .for_each(|((p, g), (m, v))| {
                for ((p, g), (m, v)) in p.iter_mut().zip(g).zip(m.iter_mut().zip(v)) {
                    *m = 0.9 * *m + g;
                    *v = 0.99 * *v + g * g;
                    *p -= *m * *v;
                }
            });
        std::hint::black_box((&mut p, &mut m, &mut v));
    });
    (28 * elements) as f64 / seconds
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two threads, 1,000 samples in 2 ms of steps: 1 ms of products (summed over the threads) doing
    /// 1e8 FLOP at 1e12 FLOP/s needs 0.1 ms, so 100 ns of the 500 a sample takes: 20% of its time.
    #[test]
    fn the_table_sets_each_phase_against_its_rate() {
        let mut times = Times::default();
        times.nanos[Phase::Steps as usize] = 2_000_000;
        times.work[Phase::Steps as usize] = 1_000;
        times.nanos[Phase::Products as usize] = 1_000_000;
        times.work[Phase::Products as usize] = 100_000_000;
        times.nanos[Phase::GridReads as usize] = 2_000_000;
        times.work[Phase::GridReads as usize] = 100_000;
        let rates = Rates {
            fma: 1e12,
            fma_bits: 256,
            products: ProductsRate::Fma,
            random_reads: vec![(1024, 1e9), (4096, 0.5e9)],
            random_updates: vec![(1024, 1e9), (4096, 1e9)],
            optimizer: 1e10,
            level_bytes: vec![1024, 4096],
        };
        // A corner at 1e9 /s on one level and 0.5e9 on the other: 2 / (1 ns + 2 ns) per second.
        assert!((rates.corners(&rates.random_reads) - 2.0 / 3.0 * 1e9).abs() < 1.0);
        let table = table(&times, &rates, 2);
        let row = |name: &str| {
            table
                .lines()
                .find(|l| l.trim_start().starts_with(name))
                .unwrap()
                .to_string()
        };
        // Products: 500 ns a sample of the 2,000 a step takes (25%), 1e5 FLOP a sample, limit 100 ns.
        let products = row("products");
        assert!(
            products.contains("25.0%") && products.contains("500.0"),
            "{products}"
        );
        assert!(
            products.contains("100000 FLOP") && products.contains("100.00") && products.ends_with("20.0%")
        );
        // Grid reads: 1,000 ns a sample, 100 corners at 1.5 ns each: 150 ns, 15% of its time.
        let reads = row("grid reads");
        assert!(
            reads.contains("1000.0") && reads.contains("150.00") && reads.ends_with("15.0%"),
            "{reads}"
        );
        // The rest: 2,000 − 500 − 1,000 = 500 ns; the step's limit 250 ns of 2,000: 12.5%.
        assert!(row("the rest").contains("500.0"), "{table}");
        let step = row("step:");
        assert!(
            step.contains("0.500 M samples/s") && step.contains("250.00 ns/sample"),
            "{step}"
        );
        assert!(step.ends_with("12.5% of that"), "{step}");
    }
}
