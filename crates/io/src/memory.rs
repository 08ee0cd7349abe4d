//! How much memory an operation may take, and the check every large allocation goes through:
//! a size a file or flag sets is compared with the budget before anything is allocated, so that
//! a bad field is an error naming it instead of an abort or an OOM kill.
//!
//! The budget is what the kernel says new allocations can get without swapping
//! (`MemAvailable` in `/proc/meminfo`), or less when the environment variable
//! [`MAX_MEMORY_VAR`] caps it (bytes, or with a `K`, `M` or `G` suffix: a share of a server
//! that others use too).

/// The environment variable that caps the memory budget.
pub const MAX_MEMORY_VAR: &str = "F3G_MAX_MEMORY";

/// How many bytes operations may take, and where that number comes from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Budget {
    pub bytes: u64,
    pub source: String,
}

/// An operation would need more memory than the budget.
#[derive(Debug, thiserror::Error)]
#[error(
    "{what} needs about {:.1} GiB of memory but only {:.1} GiB is available ({})",
    gib(*.needed),
    gib(.budget.bytes),
    .budget.source
)]
pub struct NotEnoughMemory {
    /// What needs it, as the user can change it (a flag, a configuration key, a file's field).
    pub what: String,
    pub needed: u64,
    pub budget: Budget,
}

fn gib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 30) as f64
}

/// The memory budget now: the smaller of `MemAvailable` and [`MAX_MEMORY_VAR`]; `None` when
/// neither is known (not Linux and no cap).
pub fn budget() -> Option<Budget> {
    let cap = std::env::var(MAX_MEMORY_VAR).ok().map(|v| parse_cap(&v));
    let free = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|t| mem_available(&t))
        .map(|bytes| Budget {
            bytes,
            source: "MemAvailable".into(),
        });
    match (cap, free) {
        (Some(c), Some(f)) => Some(if c.bytes < f.bytes { c } else { f }),
        (c, f) => c.or(f),
    }
}

/// The cap a [`MAX_MEMORY_VAR`] value sets; a value that is not a size allows nothing, and the
/// error then says why.
fn parse_cap(value: &str) -> Budget {
    let v = value.trim();
    let (digits, unit) = match v.char_indices().last() {
        Some((i, 'K' | 'k')) => (&v[..i], 1u64 << 10),
        Some((i, 'M' | 'm')) => (&v[..i], 1 << 20),
        Some((i, 'G' | 'g')) => (&v[..i], 1 << 30),
        _ => (v, 1),
    };
    match digits
        .trim()
        .parse::<u64>()
        .ok()
        .and_then(|d| d.checked_mul(unit))
    {
        Some(bytes) => Budget {
            bytes,
            source: format!("{MAX_MEMORY_VAR}={v}"),
        },
        None => Budget {
            bytes: 0,
            source: format!("{MAX_MEMORY_VAR}=`{v}` is not a size such as 8G, 512M or 1000000"),
        },
    }
}

/// The `MemAvailable:` line of a `/proc/meminfo` text, in bytes.
fn mem_available(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let mut words = line.split_whitespace().skip(1);
    let value: u64 = words.next()?.parse().ok()?;
    match words.next() {
        Some("kB") => value.checked_mul(1024),
        None => Some(value),
        Some(_) => None,
    }
}

/// Fails when `bytes` — an estimate of what `what` needs — exceeds `budget` (unknown: always
/// passes). The message names `what` so the user knows which flag or field to change.
pub fn ensure_fits(bytes: u64, budget: Option<Budget>, what: &str) -> Result<(), NotEnoughMemory> {
    match budget {
        Some(b) if bytes > b.bytes => Err(NotEnoughMemory {
            what: what.to_string(),
            needed: bytes,
            budget: b,
        }),
        _ => Ok(()),
    }
}

/// [`ensure_fits`] against the budget now.
pub fn ensure_available(bytes: u64, what: &str) -> Result<(), NotEnoughMemory> {
    ensure_fits(bytes, budget(), what)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mem_available_is_read_in_bytes() {
        let text =
            "MemTotal:       24000000 kB\nMemFree:         1000 kB\nMemAvailable:   20000000 kB\n";
        assert_eq!(mem_available(text), Some(20_000_000 * 1024));
        assert_eq!(mem_available("MemTotal: 5 kB\n"), None);
        assert_eq!(mem_available("MemAvailable: lots kB\n"), None);
        assert_eq!(mem_available("MemAvailable: 7 MB\n"), None);
        // This machine reports something plausible.
        if let Some(b) = budget() {
            assert!(b.bytes > 1 << 20, "{b:?}");
        }
    }

    #[test]
    fn caps_are_sizes_with_units_and_anything_else_allows_nothing() {
        assert_eq!(parse_cap("8G").bytes, 8 << 30);
        assert_eq!(parse_cap(" 512m ").bytes, 512 << 20);
        assert_eq!(parse_cap("1000").bytes, 1000);
        assert_eq!(parse_cap("3K").bytes, 3 << 10);
        for bad in ["", "lots", "-1G", "1.5G", "99999999999999999999G"] {
            let b = parse_cap(bad);
            assert_eq!(b.bytes, 0, "{bad}");
            assert!(b.source.contains("is not a size"), "{b:?}");
        }
    }

    #[test]
    fn a_request_larger_than_the_budget_names_what_needs_it_and_the_limit() {
        let budget = |bytes| {
            Some(Budget {
                bytes,
                source: "MemAvailable".into(),
            })
        };
        let e = ensure_fits(3 << 30, budget(1 << 30), "--points 100000000")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--points 100000000")
                && e.contains("3.0 GiB")
                && e.contains("1.0 GiB")
                && e.contains("(MemAvailable)"),
            "{e}"
        );
        assert!(ensure_fits(1 << 30, budget(3 << 30), "x").is_ok());
        assert!(ensure_fits(u64::MAX, None, "x").is_ok());
    }
}
