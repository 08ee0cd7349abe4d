//! Test support for the parsers' fuzz tests (a dev-dependency only; nothing ships with it).
//!
//! - [`mutated`]: a proptest strategy of byte-level mutations of a valid file (flips,
//!   truncations, insertions, deletions, and numbers spliced in: huge, negative, NaN), the
//!   inputs a file from another tool, a bad disk or a hostile user can produce.
//! - [`AllocationGuard`]: a global allocator for a test binary that refuses any single
//!   allocation above a limit, so a parser that trusts a size field fails its test (the
//!   process stops with "memory allocation of N bytes failed") instead of taking the machine's
//!   memory; [`AllocationGuard::largest`] reports the largest request seen.
//!
//! A fuzz test reads: for every mutation of a valid file, the parser returns `Ok` or an error
//! — it never panics (proptest reports a panic as a failing case, with the input shrunk) and
//! never allocates more than the guard's limit.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use proptest::prelude::*;

/// One edit of a byte string; positions are taken modulo the current length.
#[derive(Clone, Debug)]
pub enum Mutation {
    /// XOR a byte with a non-zero mask.
    Flip(usize, u8),
    /// Keep only the first `n` bytes (mod length).
    Truncate(usize),
    /// Insert bytes.
    Insert(usize, Vec<u8>),
    /// Remove up to `len` bytes.
    Delete(usize, usize),
    /// Overwrite with the text of a number that parsers should doubt.
    Number(usize, &'static str),
}

/// Numbers that break naive parsers: sizes past every limit, negative, non-finite, overflowing.
const NUMBERS: [&str; 12] = [
    "0",
    "-1",
    "4294967295",
    "18446744073709551615",
    "99999999999999999999999",
    "1e308",
    "-1e308",
    "NaN",
    "nan",
    "inf",
    "100000",
    "3.5",
];

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        (any::<usize>(), 1u8..=255).prop_map(|(p, m)| Mutation::Flip(p, m)),
        any::<usize>().prop_map(Mutation::Truncate),
        (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(p, b)| Mutation::Insert(p, b)),
        (any::<usize>(), 1usize..64).prop_map(|(p, n)| Mutation::Delete(p, n)),
        (any::<usize>(), prop::sample::select(&NUMBERS[..]))
            .prop_map(|(p, s)| Mutation::Number(p, s)),
    ]
}

/// Applies `mutations` to `bytes` in order.
pub fn apply(bytes: &[u8], mutations: &[Mutation]) -> Vec<u8> {
    let mut out = bytes.to_vec();
    for m in mutations {
        let len = out.len().max(1);
        match m {
            Mutation::Flip(p, mask) => {
                if !out.is_empty() {
                    out[p % len] ^= mask;
                }
            }
            Mutation::Truncate(n) => out.truncate(n % len),
            Mutation::Insert(p, b) => {
                let at = p % (out.len() + 1);
                out.splice(at..at, b.iter().copied());
            }
            Mutation::Delete(p, n) => {
                if !out.is_empty() {
                    let at = p % len;
                    let end = (at + n).min(out.len());
                    out.drain(at..end);
                }
            }
            Mutation::Number(p, s) => {
                let at = p % (out.len() + 1);
                // Replace the number (or byte) at the position, so fields change value.
                let end = out[at..]
                    .iter()
                    .position(|b| !(b.is_ascii_digit() || b"+-.eE".contains(b)))
                    .map_or(out.len(), |k| at + k.max(1).min(out.len() - at));
                out.splice(at..end, s.bytes());
            }
        }
    }
    out
}

/// Mutated copies of `valid`: one to five edits each.
pub fn mutated(valid: Vec<u8>) -> impl Strategy<Value = Vec<u8>> {
    prop::collection::vec(mutation(), 1..6).prop_map(move |ms| apply(&valid, &ms))
}

/// Mutated copies of the text `valid`, kept as text (lossily: invalid UTF-8 becomes U+FFFD),
/// for parsers that take `&str`.
pub fn mutated_text(valid: &str) -> impl Strategy<Value = String> + use<> {
    mutated(valid.as_bytes().to_vec()).prop_map(|b| String::from_utf8_lossy(&b).into_owned())
}

/// Proptest settings of the fuzz tests: `cases` per property, no persistence files.
pub fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        cases,
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

/// A global allocator that refuses single allocations above `limit` bytes and remembers the
/// largest request. Install it in a fuzz test binary:
/// `#[global_allocator] static GUARD: AllocationGuard = AllocationGuard::new(1 << 30);`
pub struct AllocationGuard {
    limit: usize,
    largest: AtomicUsize,
}

impl AllocationGuard {
    pub const fn new(limit: usize) -> Self {
        Self {
            limit,
            largest: AtomicUsize::new(0),
        }
    }

    /// The largest single allocation requested so far, bytes.
    pub fn largest(&self) -> usize {
        self.largest.load(Ordering::Relaxed)
    }

    fn admit(&self, size: usize) -> bool {
        self.largest.fetch_max(size, Ordering::Relaxed);
        size <= self.limit
    }
}

// SAFETY: every call forwards to the system allocator with the caller's layout and pointer;
// refusing returns null, which `GlobalAlloc` permits for failed allocations.
unsafe impl GlobalAlloc for AllocationGuard {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if !self.admit(layout.size()) {
            return std::ptr::null_mut();
        }
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if !self.admit(layout.size()) {
            return std::ptr::null_mut();
        }
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if !self.admit(new_size) {
            return std::ptr::null_mut();
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mutations_edit_as_described() {
        let base = b"width 640 height 480";
        assert_eq!(apply(base, &[Mutation::Truncate(5)]), b"width");
        assert_eq!(
            apply(base, &[Mutation::Flip(0, 0x20)]),
            b"Width 640 height 480"
        );
        assert_eq!(
            apply(base, &[Mutation::Number(6, "100000")]),
            b"width 100000 height 480"
        );
        assert_eq!(apply(base, &[Mutation::Delete(5, 4)]), b"width height 480");
        assert_eq!(
            apply(base, &[Mutation::Insert(0, b"x".to_vec())]),
            b"xwidth 640 height 480"
        );
        assert_eq!(
            apply(b"", &[Mutation::Flip(3, 1), Mutation::Delete(0, 3)]),
            b""
        );
    }
}
