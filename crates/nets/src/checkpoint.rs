//! Module files: Burn's burnpack format, written atomically, loaded with shape and finiteness
//! checks whose errors name the file and the tensor.

use std::path::Path;

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param, ParamId};
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
/// missing, extra or differently shaped tensor, or one holding NaN or infinity (a damaged file
/// would otherwise load into a network that renders garbage), is an error naming it.
pub fn load<M: Module>(module: M, path: &Path) -> Result<M, NetsError> {
    let record = burn::store::ModuleRecord::load(path)
        .map_err(|e| NetsError::weights(path, format!("cannot read a module checkpoint: {e}")))?;
    let module = module
        .try_load_record(record)
        .map_err(|e| NetsError::weights(path, e))?;
    match first_non_finite(&module) {
        Some(name) => Err(NetsError::weights(
            path,
            format!("tensor `{name}` holds NaN or infinite values"),
        )),
        None => Ok(module),
    }
}

/// The path of the first parameter holding a NaN or an infinity. One boolean comes back to the
/// host per parameter.
fn first_non_finite<M: Module>(module: &M) -> Option<String> {
    #[derive(Default)]
    struct Finite {
        path: Vec<String>,
        first: Option<String>,
    }
    impl ModuleVisitor for Finite {
        fn enter_module(&mut self, name: &str, _container: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _name: &str, _container: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let tensor = param.val();
            // x − x is NaN exactly where x is NaN or infinite.
            if self.first.is_none()
                && (tensor.clone() - tensor)
                    .is_nan()
                    .any()
                    .into_scalar::<bool>()
            {
                self.first = Some(self.path.join("."));
            }
        }
    }
    let mut visitor = Finite::default();
    module.visit(&mut visitor);
    visitor.first
}

/// Checks an optimiser's state file (burnpack bytes) against the module it steps, before Burn
/// reads it. Burn trusts the file: a state tensor without a parameter id panics while loading,
/// and one whose shape is not its parameter's panics at the next step. So every tensor must
/// belong to a parameter of `module`, have that parameter's shape, and hold finite `f32`s.
pub fn check_optimiser_state<M: Module>(bytes: &Bytes, module: &M) -> Result<(), String> {
    use burn::store::burn_pack::Reader;
    use burn::tensor::DType;
    struct Shapes(std::collections::HashMap<u64, Vec<usize>>);
    impl ModuleVisitor for Shapes {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.insert(param.id.val(), param.lazy_shape().to_vec());
        }
    }
    let mut shapes = Shapes(Default::default());
    module.visit(&mut shapes);
    let reader = Reader::from_bytes(bytes.clone()).map_err(|e| e.to_string())?;
    for tensor in reader.into_tensors().map_err(|e| e.to_string())? {
        let (name, dtype, shape, id, data) = tensor.into_parts().map_err(|e| e.to_string())?;
        let Some(expected) = id.and_then(|id| shapes.0.get(&id)) else {
            return Err(format!(
                "state `{name}` belongs to no parameter of the network (another model's file?)"
            ));
        };
        if shape.as_slice() != expected.as_slice() || dtype != DType::F32 {
            return Err(format!(
                "state `{name}` is {dtype:?} {:?}; its parameter is F32 {expected:?}",
                shape.as_slice()
            ));
        }
        if data.len() != 4 * expected.iter().product::<usize>() {
            return Err(format!("state `{name}` holds {} bytes", data.len()));
        }
        let finite = data
            .chunks_exact(4)
            .all(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]).is_finite());
        if !finite {
            return Err(format!("state `{name}` holds NaN or infinite values"));
        }
    }
    Ok(())
}
