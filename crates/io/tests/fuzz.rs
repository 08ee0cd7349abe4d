//! Fuzzing the `.npy` reader (body parameters, templates and PCA files come as `.npy`/`.npz`):
//! for thousands of mutations of a valid file, reading returns an array whose shape matches
//! its values, or an error naming the file — no panic, no single allocation above 256 MiB
//! however large a shape the header claims.

use f3g_io::{encode_npy_f32, read_npy_f32};
use f3g_testkit::{AllocationGuard, config, mutated};
use proptest::prelude::*;

#[global_allocator]
static GUARD: AllocationGuard = AllocationGuard::new(256 << 20);

fn valid() -> Vec<u8> {
    let data: Vec<f32> = (0..24).map(|i| i as f32 * 0.25).collect();
    encode_npy_f32(&[2, 3, 4], &data).unwrap()
}

#[test]
fn a_header_that_claims_a_huge_shape_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("a.npy");
    let text = String::from_utf8_lossy(&valid()).into_owned();
    let huge = text.replace("(2, 3, 4)", "(200000, 300000, 4000)");
    std::fs::write(&path, huge.as_bytes()).unwrap();
    let e = read_npy_f32(&path).unwrap_err().to_string();
    assert!(e.contains("a.npy"), "{e}");
    // A well-formed header whose shape's product overflows 64 bits (it would wrap round to
    // a small element count).
    let dict = "{'descr': '<f4', 'fortran_order': False, 'shape': (6148914691236517206, 3, 4), }";
    let mut header = format!("{dict:<118}\n");
    while (10 + header.len()) % 64 != 0 {
        header.insert(header.len() - 1, ' ');
    }
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend((header.len() as u16).to_le_bytes());
    bytes.extend(header.as_bytes());
    bytes.extend([0u8; 96]);
    std::fs::write(&path, &bytes).unwrap();
    let e = read_npy_f32(&path).unwrap_err().to_string();
    assert!(e.contains("a.npy") && e.contains("more values"), "{e}");
}

proptest! {
    #![proptest_config(config(3000))]

    #[test]
    fn mutated_npy_reads_or_errors(bytes in mutated(valid())) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.npy");
        std::fs::write(&path, &bytes).unwrap();
        match read_npy_f32(&path) {
            Ok((shape, values)) => prop_assert_eq!(shape.iter().product::<usize>(), values.len()),
            Err(e) => prop_assert!(e.to_string().contains("a.npy"), "{}", e),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }
}
