//! Module files: Burn's burnpack format, written atomically, loaded with shape checks whose
//! errors name the file and the tensor.

use std::path::Path;

use burn::module::{Module, ModuleMapper, Param, ParamId};
use burn::tensor::{Bytes, Tensor};

use crate::NetsError;

/// Writes `module`'s parameters to `path` (temporary file, then rename).
pub fn save<M: Module>(module: M, path: &Path) -> Result<(), NetsError> {
    let bytes = module
        .into_record()
        .into_bytes()
        .map_err(|e| NetsError::weights(path, e))?;
    f3g_io::write_atomic(path, &bytes).map_err(|e| NetsError::weights(path, e.reason))
}

/// `module` with parameter ids that are a function of `namespace` and each parameter's place in
/// the module. Burn draws ids at random and stores them in module and optimiser files, so two
/// identical runs would write different bytes; with these ids they write the same files, and a
/// run can be verified by hash. Modules that may meet in one optimiser or gradient set need
/// different namespaces.
pub fn with_deterministic_ids<M: Module>(module: M, namespace: u64) -> M {
    struct Ids {
        namespace: u64,
        next: u64,
    }
    impl ModuleMapper for Ids {
        fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
            let (_, value, mapper) = param.consume();
            // SplitMix64 of (namespace, index): distinct, well-spread 64-bit ids.
            let mut z = self
                .namespace
                .wrapping_mul(0x9E37_79B9_7F4A_7C15)
                .wrapping_add(self.next);
            self.next += 1;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            Param::from_mapped_value(ParamId::from(z ^ (z >> 31)), value, mapper)
        }
    }
    module.map(&mut Ids { namespace, next: 0 })
}

/// A burnpack buffer rewritten with its tensors in name order. Burn writes an optimiser's state
/// in the iteration order of a `HashMap`, which differs between processes; reading orders the
/// tensors by name, so writing them back gives the same bytes for the same contents. (Module
/// files need no such pass: [`save`] writes them in the module's own visiting order.)
pub fn canonical_burnpack(bytes: Bytes) -> Result<Bytes, String> {
    use burn::store::burn_pack::{Reader, Writer};
    let reader = Reader::from_bytes(bytes).map_err(|e| e.to_string())?;
    let metadata = reader.metadata().clone();
    let scalars = reader.scalars().clone();
    let tensors = reader.into_tensors().map_err(|e| e.to_string())?;
    let mut writer = Writer::new(tensors);
    for (key, value) in &metadata {
        writer = writer.with_metadata(key, value);
    }
    for (key, value) in scalars {
        writer = writer.with_scalar(&key, value);
    }
    writer.into_bytes().map_err(|e| e.to_string())
}

/// Loads parameters saved by [`save`] into `module`, which must have the same structure: a
/// missing, extra or differently shaped tensor is an error naming it.
pub fn load<M: Module>(module: M, path: &Path) -> Result<M, NetsError> {
    let record = burn::store::ModuleRecord::load(path)
        .map_err(|e| NetsError::weights(path, format!("cannot read a module checkpoint: {e}")))?;
    module
        .try_load_record(record)
        .map_err(|e| NetsError::weights(path, e))
}
