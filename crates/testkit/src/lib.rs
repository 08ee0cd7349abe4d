//! Test support for the parsers' fuzz tests (a dev-dependency only; nothing ships with it).
//!
//! - [`mutated`]: a proptest strategy of byte-level mutations of a valid file (flips,
//!   truncations, insertions, deletions, and numbers spliced in: huge, negative, NaN), the
//!   inputs a file from another tool, a bad disk or a hostile user can produce.
//! - [`mutated_arrays`]: structure-aware mutations of the named arrays of a valid `.npz`
//!   (an array dropped, renamed, reshaped, retyped, or a value poisoned with NaN or a huge
//!   number), written with [`write_arrays`]: byte flips of a zip archive mostly break its
//!   checksums, these reach the readers' shape and value checks.
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

/// Proptest settings of the fuzz tests: `cases` per property, no persistence files, and a
/// fixed seed so that a test run (CI's included) is reproducible. `F3G_FUZZ_SEED=N` explores
/// other inputs: run a few seeds after changing a parser.
pub fn config(cases: u32) -> ProptestConfig {
    let seed = std::env::var("F3G_FUZZ_SEED")
        .ok()
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(0xF3_5EED);
    ProptestConfig {
        cases,
        failure_persistence: None,
        rng_seed: proptest::test_runner::RngSeed::Fixed(seed),
        ..ProptestConfig::default()
    }
}

/// The values of one array of an `.npz`.
#[derive(Clone, Debug, PartialEq)]
pub enum Values {
    F32(Vec<f32>),
    I64(Vec<i64>),
}

impl Values {
    fn len(&self) -> usize {
        match self {
            Values::F32(v) => v.len(),
            Values::I64(v) => v.len(),
        }
    }

    /// Cycles (or cuts) the values to `n`, padding an empty array with ones.
    fn resized(&self, n: usize) -> Values {
        fn cycle<T: Copy>(v: &[T], n: usize, one: T) -> Vec<T> {
            (0..n)
                .map(|i| if v.is_empty() { one } else { v[i % v.len()] })
                .collect()
        }
        match self {
            Values::F32(v) => Values::F32(cycle(v, n, 1.0)),
            Values::I64(v) => Values::I64(cycle(v, n, 1)),
        }
    }
}

/// One named array of an `.npz`.
#[derive(Clone, Debug, PartialEq)]
pub struct Array {
    pub name: String,
    pub shape: Vec<usize>,
    pub values: Values,
}

impl Array {
    pub fn f32(name: &str, shape: &[usize], values: &[f32]) -> Self {
        Self::new(name, shape, Values::F32(values.to_vec()))
    }

    pub fn i64(name: &str, shape: &[usize], values: &[i64]) -> Self {
        Self::new(name, shape, Values::I64(values.to_vec()))
    }

    fn new(name: &str, shape: &[usize], values: Values) -> Self {
        assert_eq!(shape.iter().product::<usize>(), values.len(), "`{name}`");
        Self {
            name: name.to_string(),
            shape: shape.to_vec(),
            values,
        }
    }
}

/// Reads every array of an `.npz` (f32 or integer) so a valid file can seed [`mutated_arrays`].
pub fn read_arrays(path: &std::path::Path) -> Vec<Array> {
    let mut npz = f3g_io::Npz::open(path).expect("a readable seed file");
    let mut names = npz.names();
    // The archive's listing order is not stable; name order keeps mutations reproducible.
    names.sort();
    names
        .into_iter()
        // Integers first: the f32 reader also accepts integer arrays.
        .map(|name| match npz.i64(&name) {
            Ok((shape, v)) => Array::i64(&name, &shape, &v),
            Err(_) => {
                let (shape, v) = npz.f32(&name).expect("f32 or integer arrays");
                Array::f32(&name, &shape, &v)
            }
        })
        .collect()
}

/// Writes arrays as an `.npz` (with `f3g_io::write_npz`).
pub fn write_arrays(path: &std::path::Path, arrays: &[Array]) {
    let arrays: Vec<(&str, &[usize], f3g_io::NpyValues<'_>)> = arrays
        .iter()
        .map(|a| {
            let values = match &a.values {
                Values::F32(v) => f3g_io::NpyValues::F32(v),
                Values::I64(v) => f3g_io::NpyValues::I64(v),
            };
            (a.name.as_str(), a.shape.as_slice(), values)
        })
        .collect();
    f3g_io::write_npz(path, &arrays).expect("writing a test file");
}

/// One edit of a list of arrays; indices are taken modulo the current lengths.
#[derive(Clone, Debug)]
pub enum ArrayEdit {
    Drop(usize),
    Rename(usize),
    /// Set dimension `dim` of an array to a new size (values cycled to fit).
    Resize {
        array: usize,
        dim: usize,
        size: usize,
    },
    /// Add a leading dimension of 1, or remove the first one (values kept).
    Rank(usize, bool),
    /// Store f32 values as integers or integers as f32.
    Retype(usize),
    /// Overwrite one value with a number readers should doubt.
    Poison {
        array: usize,
        at: usize,
        which: usize,
    },
}

const POISON_F32: [f32; 6] = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 1e30, -1.0, 0.0];
const POISON_I64: [i64; 6] = [-1, i64::MAX, i64::MIN, 1 << 40, 4_294_967_296, 1_000_000];
/// New sizes of a dimension; small ones keep the files (and tests) small.
const SIZES: [usize; 7] = [0, 1, 2, 3, 4, 7, 64];

fn array_edit() -> impl Strategy<Value = ArrayEdit> {
    prop_oneof![
        any::<usize>().prop_map(ArrayEdit::Drop),
        any::<usize>().prop_map(ArrayEdit::Rename),
        (
            any::<usize>(),
            any::<usize>(),
            prop::sample::select(&SIZES[..])
        )
            .prop_map(|(array, dim, size)| ArrayEdit::Resize { array, dim, size }),
        (any::<usize>(), any::<bool>()).prop_map(|(a, add)| ArrayEdit::Rank(a, add)),
        any::<usize>().prop_map(ArrayEdit::Retype),
        (any::<usize>(), any::<usize>(), 0..POISON_F32.len())
            .prop_map(|(array, at, which)| ArrayEdit::Poison { array, at, which }),
    ]
}

/// Applies `edits` to `arrays` in order.
pub fn edit_arrays(arrays: &[Array], edits: &[ArrayEdit]) -> Vec<Array> {
    let mut out = arrays.to_vec();
    for edit in edits {
        if out.is_empty() {
            break;
        }
        let n = out.len();
        match *edit {
            ArrayEdit::Drop(k) => {
                out.remove(k % n);
            }
            ArrayEdit::Rename(k) => out[k % n].name.push('_'),
            ArrayEdit::Resize { array, dim, size } => {
                let a = &mut out[array % n];
                if !a.shape.is_empty() {
                    let d = dim % a.shape.len();
                    a.shape[d] = size;
                    a.values = a.values.resized(a.shape.iter().product());
                }
            }
            ArrayEdit::Rank(k, add) => {
                let a = &mut out[k % n];
                if add {
                    a.shape.insert(0, 1);
                } else if !a.shape.is_empty() {
                    let first = a.shape.remove(0);
                    if let Some(next) = a.shape.first_mut() {
                        *next *= first;
                    } else {
                        a.shape.push(first);
                    }
                }
            }
            ArrayEdit::Retype(k) => {
                let a = &mut out[k % n];
                a.values = match &a.values {
                    Values::F32(v) => Values::I64(v.iter().map(|&x| x as i64).collect()),
                    Values::I64(v) => Values::F32(v.iter().map(|&x| x as f32).collect()),
                };
            }
            ArrayEdit::Poison { array, at, which } => {
                let a = &mut out[array % n];
                let len = a.values.len();
                if len > 0 {
                    match &mut a.values {
                        Values::F32(v) => v[at % len] = POISON_F32[which],
                        Values::I64(v) => v[at % len] = POISON_I64[which],
                    }
                }
            }
        }
    }
    out
}

/// Mutated copies of the arrays of a valid `.npz`: one to four edits each.
pub fn mutated_arrays(valid: Vec<Array>) -> impl Strategy<Value = Vec<Array>> {
    prop::collection::vec(array_edit(), 1..5).prop_map(move |es| edit_arrays(&valid, &es))
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
        // SAFETY: `layout` has a non-zero size (the caller's contract for `alloc`), all
        // `System` needs.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if !self.admit(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: `layout` has a non-zero size (the caller's contract for `alloc_zeroed`), all
        // `System` needs.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: the caller's `ptr` was allocated with `layout` by this allocator, that is by
        // `System`, which allocates every block here.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if !self.admit(new_size) {
            return std::ptr::null_mut();
        }
        // SAFETY: the caller's `ptr` is a block of `System`'s allocated with `layout`, and
        // `new_size` is non-zero and fits `isize` when rounded to the alignment (`realloc`'s
        // contract).
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn array_edits_keep_shapes_and_values_consistent() {
        let valid = vec![
            Array::f32("a", &[2, 3], &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0]),
            Array::i64("b", &[2], &[7, 8]),
        ];
        let resized = edit_arrays(
            &valid,
            &[ArrayEdit::Resize {
                array: 0,
                dim: 1,
                size: 4,
            }],
        );
        assert_eq!(resized[0].shape, [2, 4]);
        assert_eq!(
            resized[0].values,
            Values::F32(vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 0.0, 1.0])
        );
        let flat = edit_arrays(&valid, &[ArrayEdit::Rank(0, false)]);
        assert_eq!(flat[0].shape, [6]);
        let retyped = edit_arrays(&valid, &[ArrayEdit::Retype(1), ArrayEdit::Drop(0)]);
        assert_eq!(retyped, vec![Array::f32("b", &[2], &[7.0, 8.0])]);
        let poisoned = edit_arrays(
            &valid,
            &[ArrayEdit::Poison {
                array: 1,
                at: 3,
                which: 0,
            }],
        );
        assert_eq!(poisoned[1].values, Values::I64(vec![7, -1]));
        let dir = std::env::temp_dir().join(format!("f3g-testkit-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.npz");
        write_arrays(&path, &valid);
        assert_eq!(read_arrays(&path), valid);
        std::fs::remove_dir_all(&dir).unwrap();
    }

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
