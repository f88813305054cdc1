//! Memory: what this process can still take, the default budget that large work is checked
//! against before it starts, and the peak resident set the benches report. Used by the readers
//! (`io`), the density grid, the refinement and the renders' buffers alike.

/// The memory budget of decompression when reading, and of the density grid
/// ([`crate::pipeline::GridParams::memory_budget`]): 1 GiB.
pub const DEFAULT_MEMORY_BUDGET: u64 = 1 << 30;

/// Memory this process can still take, in bytes: the machine's `MemAvailable`, lowered to what
/// is left under the process's address-space limit (`ulimit -v`) when one is set; 8 GiB where
/// neither is known.
#[must_use]
pub fn available_memory() -> u64 {
    let field = |text: &str, key: &str| {
        text.lines().find(|l| l.starts_with(key)).and_then(|l| {
            l[key.len()..]
                .split_whitespace()
                .next()?
                .parse::<u64>()
                .ok()
        })
    };
    let machine = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| field(&s, "MemAvailable:"))
        .map_or(8 << 30, |kib| kib * 1024);
    // "Max address space  <soft> <hard> bytes"; the soft limit is the one that fails allocations
    let limit = std::fs::read_to_string("/proc/self/limits")
        .ok()
        .and_then(|s| field(&s, "Max address space"));
    match limit {
        Some(limit) => {
            let used = std::fs::read_to_string("/proc/self/status")
                .ok()
                .and_then(|s| field(&s, "VmSize:"))
                .map_or(0, |kib| kib * 1024);
            machine.min(limit.saturating_sub(used))
        }
        None => machine,
    }
}

/// This process's peak resident set so far, in MiB (`VmHWM` of `/proc/self/status`); `None`
/// where the system does not report it. What the benches and `refine --json` report as peak
/// memory.
#[must_use]
pub fn peak_resident_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Resets [`peak_resident_mib`] to the present resident set (Linux `/proc/self/clear_refs`), so
/// that a later reading is the peak of what ran in between; false where that is not available.
pub fn reset_peak_resident() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}
