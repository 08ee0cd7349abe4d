//! Fuzzing module checkpoints (`*.bpk`: files that outlive the binary, copied between
//! machines, truncated by full disks): for mutations of a valid file's bytes, loading gives a
//! network with finite parameters that runs, or an error naming the file — no panic, no single allocation
//! above 256 MiB whatever sizes the damaged header claims.

mod common;

use burn::module::Module;
use burn::tensor::Device;
use f3g_nets::{StyleUNetConfig, checkpoint};
use f3g_testkit::{AllocationGuard, config, mutated};
use proptest::prelude::*;

#[global_allocator]
static GUARD: AllocationGuard = AllocationGuard::new(256 << 20);

fn small() -> StyleUNetConfig {
    StyleUNetConfig {
        input_size: 16,
        output_size: 16,
        channel_base: 32,
        max_channels: 4,
        style_dim: 4,
        middle_size: 4,
        ..StyleUNetConfig::cpu_face(3, false)
    }
}

static SEED: std::sync::LazyLock<Vec<u8>> = std::sync::LazyLock::new(|| {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("net.bpk");
    checkpoint::save(small().init(1, &Device::flex()).unwrap(), &path).unwrap();
    std::fs::read(&path).unwrap()
});

#[test]
fn the_seed_loads_and_a_poisoned_weight_is_named() {
    let device = Device::flex();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("net.bpk");
    std::fs::write(&path, &*SEED).unwrap();
    checkpoint::load(small().init(2, &device).unwrap(), &path).unwrap();
    // Every f32 of the file that equals a weight of the first tensor set to NaN: the file
    // still parses, and only the finiteness check can catch it.
    let net = small().init(1, &device).unwrap();
    let nan = net.map(&mut Poison);
    checkpoint::save(nan, &path).unwrap();
    let e = checkpoint::load(small().init(2, &device).unwrap(), &path)
        .unwrap_err()
        .to_string();
    assert!(e.contains("net.bpk") && e.contains("NaN"), "{e}");
}

/// Sets the first element of every float parameter to NaN.
struct Poison;

impl burn::module::ModuleMapper for Poison {
    fn map_float<const D: usize>(
        &mut self,
        param: burn::module::Param<burn::tensor::Tensor<D>>,
    ) -> burn::module::Param<burn::tensor::Tensor<D>> {
        param.map(|t| {
            let mut data = t.to_data().convert::<f32>();
            data.as_mut_slice::<f32>().unwrap()[0] = f32::NAN;
            burn::tensor::Tensor::from_data(data, &t.device())
        })
    }
}

proptest! {
    #![proptest_config(config(500))]

    #[test]
    fn mutated_checkpoints_load_or_error(bytes in mutated(SEED.clone())) {
        let device = Device::flex();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("net.bpk");
        std::fs::write(&path, &bytes).unwrap();
        match checkpoint::load(small().init(2, &device).unwrap(), &path) {
            Ok(net) => {
                let out = net.forward(common::ramp([1, 3, 16, 16], &device), None).unwrap();
                // Finite weights may still overflow (a flipped exponent bit gives 1e38), so
                // the output's values are not checked, only that the network runs.
                prop_assert_eq!(out.front.dims(), [1, 3, 16, 16]);
            }
            Err(e) => prop_assert!(e.to_string().contains("net.bpk"), "{}", e),
        }
        prop_assert!(GUARD.largest() <= 256 << 20);
    }
}
