//! Flushing subnormal floats to zero. Training drives gradients, Adam's moments and activations into
//! the subnormal range, where x86 cores take a microcode assist per operation: a neural SDF's steps got
//! 1.6× slower over 300 steps of training with them. XLA's CPU backend and PyTorch's
//! `set_flush_denormal` make the same choice.

/// Sets flush-to-zero and denormals-are-zero on the calling thread (x86-64; elsewhere nothing).
pub fn flush_denormals() {
    #[cfg(target_arch = "x86_64")]
    {
        /// MXCSR's flush-to-zero (bit 15) and denormals-are-zero (bit 6) flags.
        const FTZ_DAZ: u32 = (1 << 15) | (1 << 6);
        let mut csr: u32 = 0;
        // SAFETY: stmxcsr/ldmxcsr read and write the thread's SSE control register through a
        // 4-byte local; setting FTZ and DAZ changes only how subnormal results and inputs round.
        unsafe {
            std::arch::asm!("stmxcsr [{0}]", in(reg) &mut csr, options(nostack, preserves_flags));
            csr |= FTZ_DAZ;
            std::arch::asm!("ldmxcsr [{0}]", in(reg) &csr, options(nostack, preserves_flags));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subnormals_become_zero_on_the_flushed_thread_only() {
        let tiny = std::hint::black_box(f32::MIN_POSITIVE);
        let half = std::hint::black_box(0.5f32);
        let here = std::thread::spawn(move || tiny * half).join().unwrap();
        assert!(
            here > 0.0 && here < f32::MIN_POSITIVE,
            "subnormal without flushing: {here}"
        );
        let flushed = std::thread::spawn(move || {
            flush_denormals();
            // Read through black_box after the flush: the optimizer may otherwise compute the product
            // before the control register changes (floating-point operations are not ordered with it).
            std::hint::black_box(tiny) * std::hint::black_box(half)
        })
        .join()
        .unwrap();
        if cfg!(target_arch = "x86_64") {
            assert_eq!(flushed, 0.0);
        }
    }
}
