//! How much memory this process may still use: the default byte budget of the
//! volume readers, and a figure the command-line program and the memory guard can
//! reuse.
//!
//! On Linux it is the smallest of what the system, the control group and the
//! address-space limit leave: `MemAvailable` of `/proc/meminfo`; the cgroup's
//! `memory.max` (v2) or `memory.limit_in_bytes` (v1) minus its current usage; and
//! `RLIMIT_AS` minus the process's current virtual size. Elsewhere nothing is
//! known and [`usable_memory`] returns `None`.

use std::path::{Path, PathBuf};

/// The most a reader uses by default, whatever the machine has: 64 GiB.
pub const DEFAULT_MAX_BYTES: u64 = 64 << 30;

/// Bytes of memory this process may still allocate, if the platform tells us:
/// the smallest of the system's available memory, the room left under the
/// control group's limit, and the room left under `RLIMIT_AS`. `None` when none
/// of them can be read (non-Linux systems).
pub fn usable_memory() -> Option<u64> {
    [mem_available(), cgroup_room(), address_space_room()].into_iter().flatten().min()
}

/// The default budget of [`crate::read_volume`]: [`usable_memory`], at most
/// [`DEFAULT_MAX_BYTES`] (and exactly that when nothing is known).
pub fn default_budget() -> u64 {
    budget_of(usable_memory())
}

/// The budget for `usable` bytes (as [`usable_memory`] reports them): at most
/// [`DEFAULT_MAX_BYTES`], and exactly that when nothing is known.
fn budget_of(usable: Option<u64>) -> u64 {
    usable.map_or(DEFAULT_MAX_BYTES, |m| m.min(DEFAULT_MAX_BYTES))
}

/// A byte count as people read it: `512 B`, `3.0 KiB`, `1.5 GiB`.
pub fn human_bytes(bytes: u64) -> String {
    const UNITS: [&str; 6] = ["KiB", "MiB", "GiB", "TiB", "PiB", "EiB"];
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

/// `MemAvailable` of `/proc/meminfo`, in bytes.
fn mem_available() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    parse_meminfo_kib(&text, "MemAvailable:").map(|kib| kib.saturating_mul(1024))
}

/// The value in kB of one `/proc/meminfo` line such as `MemAvailable:  123 kB`.
fn parse_meminfo_kib(text: &str, key: &str) -> Option<u64> {
    text.lines().find_map(|line| line.strip_prefix(key)?.split_whitespace().next()?.parse().ok())
}

/// Room left under the memory limit of this process's control group (v2, else v1).
fn cgroup_room() -> Option<u64> {
    let membership = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    let root = Path::new("/sys/fs/cgroup");
    // v2: the line "0::/path".
    if let Some(rel) = membership.lines().find_map(|l| l.strip_prefix("0::")) {
        for dir in cgroup_dirs(root, rel) {
            if let Some(limit) = read_limit(&dir.join("memory.max")) {
                let used = read_limit(&dir.join("memory.current")).unwrap_or(0);
                return Some(limit.saturating_sub(working_set(used, &dir.join("memory.stat"), "inactive_file")));
            }
        }
    }
    // v1: the line "N:memory:/path" (or with memory among other controllers).
    let rel = membership.lines().find_map(|l| {
        let mut parts = l.splitn(3, ':');
        let (_, controllers, path) = (parts.next()?, parts.next()?, parts.next()?);
        controllers.split(',').any(|c| c == "memory").then_some(path)
    })?;
    for dir in cgroup_dirs(&root.join("memory"), rel) {
        if let Some(limit) = read_limit(&dir.join("memory.limit_in_bytes")) {
            let used = read_limit(&dir.join("memory.usage_in_bytes")).unwrap_or(0);
            return Some(limit.saturating_sub(working_set(used, &dir.join("memory.stat"), "total_inactive_file")));
        }
    }
    None
}

/// A cgroup's usage without its inactive file cache, which the kernel reclaims
/// before it would refuse memory (the "working set" of container tools).
fn working_set(used: u64, stat: &Path, key: &str) -> u64 {
    let inactive = std::fs::read_to_string(stat).ok().and_then(|text| {
        text.lines().find_map(|l| {
            let (k, v) = l.split_once(' ')?;
            (k == key).then(|| v.trim().parse::<u64>().ok())?
        })
    });
    used.saturating_sub(inactive.unwrap_or(0))
}

/// Where a cgroup's files may be: under its path, or at the mount's root (inside
/// a container the cgroup namespace often shows the container's own group there).
fn cgroup_dirs(root: &Path, rel: &str) -> [PathBuf; 2] {
    [root.join(rel.trim_start_matches('/')), root.to_path_buf()]
}

/// A cgroup limit file: a byte count, or `max` (no limit, `None`). v1 writes "no
/// limit" as a huge number, which the `min` with the other figures absorbs.
fn read_limit(path: &Path) -> Option<u64> {
    std::fs::read_to_string(path).ok()?.trim().parse().ok()
}

/// Room left under `RLIMIT_AS`: the limit minus the process's virtual size.
#[cfg(target_os = "linux")]
fn address_space_room() -> Option<u64> {
    let mut limit = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
    // SAFETY: getrlimit writes one `rlimit` through a valid pointer.
    if unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut limit) } != 0 || limit.rlim_cur == libc::RLIM_INFINITY {
        return None;
    }
    // /proc/self/statm: the first field is the virtual size in pages.
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().next()?.parse().ok()?;
    // SAFETY: sysconf has no preconditions.
    let page_size = u64::try_from(unsafe { libc::sysconf(libc::_SC_PAGESIZE) }).ok()?;
    // `rlim_t` is 32 bits on some 32-bit targets, 64 here.
    #[allow(clippy::useless_conversion)]
    let limit_bytes = u64::from(limit.rlim_cur);
    Some(limit_bytes.saturating_sub(pages.saturating_mul(page_size)))
}

#[cfg(not(target_os = "linux"))]
fn address_space_room() -> Option<u64> {
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn meminfo_lines_are_parsed_in_kib() {
        let text = "MemTotal:       32768 kB\nMemFree:  100 kB\nMemAvailable:   2048 kB\n";
        assert_eq!(parse_meminfo_kib(text, "MemAvailable:"), Some(2048));
        assert_eq!(parse_meminfo_kib(text, "SwapFree:"), None);
    }

    #[test]
    fn human_bytes_picks_the_unit() {
        assert_eq!(human_bytes(512), "512 B");
        assert_eq!(human_bytes(1536), "1.5 KiB");
        assert_eq!(human_bytes(512 * 512 * 4096), "1.0 GiB");
        assert_eq!(human_bytes(u64::MAX), "16.0 EiB");
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn usable_memory_is_known_on_linux_and_bounds_the_default() {
        // Two reads of the available memory differ while other processes run, so
        // the rule is checked on fixed values and the live reading only for its range.
        let usable = usable_memory().expect("/proc/meminfo is readable on Linux");
        assert!(usable > 0);
        assert!(default_budget() > 0 && default_budget() <= DEFAULT_MAX_BYTES);
        assert_eq!(budget_of(Some(1 << 30)), 1 << 30);
        assert_eq!(budget_of(Some(DEFAULT_MAX_BYTES + 1)), DEFAULT_MAX_BYTES);
        assert_eq!(budget_of(None), DEFAULT_MAX_BYTES);
    }
}
