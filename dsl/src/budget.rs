//! The memory budget: the most memory one run may plan to hold, checked before large allocations.
//!
//! Sizes that come from a script, a setting, a file header or a flag (params, training state, meshing
//! grids, loaded images) are checked against one process-wide limit before anything is allocated, so that
//! a careless or hostile size is a message naming what was asked, the bytes it needs and the limit, not an
//! abort on allocation. The limit defaults to three quarters of the machine's physical memory (less under
//! a cgroup or `ulimit -v` limit) and can be raised or lowered explicitly (`nerfjit --max-memory 20G`).

use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};

/// The limit when the machine's physical memory cannot be read.
const FALLBACK_BYTES: u64 = 16 << 30;

/// The limit set by [`set_max_memory`]; 0 until then (the default applies).
static MAX_MEMORY: AtomicU64 = AtomicU64::new(0);

/// The memory limit in bytes: the one set by [`set_max_memory`], or [`default_max_memory`].
pub fn max_memory() -> u64 {
    match MAX_MEMORY.load(Ordering::Relaxed) {
        0 => default_max_memory(),
        bytes => bytes,
    }
}

/// Sets the memory limit for the rest of the process (at least 1 byte).
pub fn set_max_memory(bytes: u64) {
    MAX_MEMORY.store(bytes.max(1), Ordering::Relaxed);
}

/// The default limit: three quarters of the physical memory (`MemTotal` of `/proc/meminfo`), of the
/// cgroup's memory limit (`/sys/fs/cgroup/memory.max`) if lower, and half the address-space limit
/// (`ulimit -v`) if lower still (the rest of the address space holds stacks, code and compiled
/// kernels). 16 GiB where none can be read.
pub fn default_max_memory() -> u64 {
    let read = |path: &str| std::fs::read_to_string(path).ok();
    let physical = read("/proc/meminfo").and_then(|text| mem_total(&text));
    let cgroup = read("/sys/fs/cgroup/memory.max").and_then(|text| text.trim().parse::<u64>().ok());
    let address_space = read("/proc/self/limits").and_then(|text| address_space_limit(&text));
    let limits = [
        physical.map(|b| b / 4 * 3),
        cgroup.map(|b| b / 4 * 3),
        address_space.map(|b| b / 2),
    ];
    limits.into_iter().flatten().min().unwrap_or(FALLBACK_BYTES)
}

/// `MemTotal` in bytes from the text of `/proc/meminfo` (given there in kB).
fn mem_total(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

/// The soft "Max address space" limit in bytes from the text of `/proc/self/limits` (`None` if
/// unlimited).
fn address_space_limit(limits: &str) -> Option<u64> {
    let line = limits.lines().find(|l| l.starts_with("Max address space"))?;
    line.split_whitespace().nth(3)?.parse().ok()
}

/// A planned allocation beyond the memory limit.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct OverBudget {
    /// What was asked, e.g. "the params (up to 'w')".
    pub what: String,
    /// The bytes it would need.
    pub bytes: u64,
    /// The limit in force.
    pub limit: u64,
}

impl fmt::Display for OverBudget {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} would need {}, more than the memory limit of {}",
            self.what,
            human_bytes(self.bytes),
            human_bytes(self.limit)
        )
    }
}

impl std::error::Error for OverBudget {}

/// The hint shown with an [`OverBudget`] error.
pub const HINT: &str = "make it smaller, or raise the limit with --max-memory (e.g. --max-memory 32G)";

/// Checks that `bytes` fit in the memory limit; `what` names the allocation for the message.
pub fn check(what: impl FnOnce() -> String, bytes: u64) -> Result<(), OverBudget> {
    let limit = max_memory();
    if bytes <= limit {
        Ok(())
    } else {
        Err(OverBudget {
            what: what(),
            bytes,
            limit,
        })
    }
}

/// The bytes of `count` items of `size` bytes each, saturating (a saturated size is over any limit).
pub fn bytes_of(count: u64, size: u64) -> u64 {
    count.saturating_mul(size)
}

/// A size such as `512M`, `20G`, `1.5GiB` or `1000000` (bytes) in bytes. Suffixes are powers of 1024.
pub fn parse_size(text: &str) -> Result<u64, String> {
    let text = text.trim();
    let digits = text
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(text.len());
    let (number, unit) = text.split_at(digits);
    let scale: u64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1,
        "k" | "kb" | "kib" => 1 << 10,
        "m" | "mb" | "mib" => 1 << 20,
        "g" | "gb" | "gib" => 1 << 30,
        "t" | "tb" | "tib" => 1 << 40,
        other => return Err(format!("unknown unit '{other}' in '{text}': use K, M, G or T")),
    };
    let value: f64 = number
        .parse()
        .map_err(|_| format!("'{text}' is not a size such as 512M or 20G"))?;
    let bytes = value * scale as f64;
    if !(1.0..=u64::MAX as f64).contains(&bytes) {
        return Err(format!("'{text}' is not a size from 1 byte to 16 EiB"));
    }
    Ok(bytes as u64)
}

/// `bytes` for people: `512 B`, `3.0 MiB`, `17.6 GiB`.
pub fn human_bytes(bytes: u64) -> String {
    const UNITS: [&str; 5] = ["KiB", "MiB", "GiB", "TiB", "PiB"];
    if bytes < 1024 {
        return format!("{bytes} B");
    }
    let mut value = bytes as f64 / 1024.0;
    let mut unit = 0;
    while value >= 1024.0 && unit + 1 < UNITS.len() {
        value /= 1024.0;
        unit += 1;
    }
    format!("{value:.1} {}", UNITS[unit])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_with_binary_units_and_bad_ones_are_refused() {
        assert_eq!(parse_size("1000"), Ok(1000));
        assert_eq!(parse_size("512M"), Ok(512 << 20));
        assert_eq!(parse_size("20G"), Ok(20 << 30));
        assert_eq!(parse_size("1.5 GiB"), Ok(3 << 29));
        assert_eq!(parse_size("2tb"), Ok(2 << 40));
        assert!(parse_size("").is_err());
        assert!(parse_size("0").is_err());
        assert!(parse_size("12X").unwrap_err().contains("unknown unit 'x'"));
        assert!(parse_size("G").is_err());
        assert!(parse_size("1e30").is_err());
    }

    #[test]
    fn bytes_print_in_the_largest_fitting_unit() {
        assert_eq!(human_bytes(512), "512 B");
        assert_eq!(human_bytes(3 << 20), "3.0 MiB");
        assert_eq!(human_bytes(16 << 30), "16.0 GiB");
        assert_eq!(human_bytes(u64::MAX), "16384.0 PiB");
    }

    #[test]
    fn memory_and_address_space_limits_are_read() {
        let text = "MemTotal:       24576000 kB\nMemFree:  1 kB\n";
        assert_eq!(mem_total(text), Some(24_576_000 * 1024));
        assert_eq!(mem_total("MemFree: 1 kB\n"), None);
        let limits = "Max processes  95000  95000  processes\n\
                      Max address space         8192000000           8192000000           bytes\n";
        assert_eq!(address_space_limit(limits), Some(8_192_000_000));
        let unlimited = "Max address space         unlimited            unlimited            bytes\n";
        assert_eq!(address_space_limit(unlimited), None);
    }

    #[test]
    fn checks_compare_with_the_limit_and_name_what_was_asked() {
        let limit = max_memory();
        assert!(limit > 0);
        assert!(check(|| "small".into(), limit).is_ok());
        let e = check(|| "the params".into(), bytes_of(u64::MAX, 4)).unwrap_err();
        assert_eq!(e.bytes, u64::MAX);
        assert!(e
            .to_string()
            .starts_with("the params would need 16384.0 PiB, more than the memory limit"));
    }
}
