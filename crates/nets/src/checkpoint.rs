//! Module files: Burn's burnpack format, written atomically, loaded with shape checks whose
//! errors name the file and the tensor.

use std::path::Path;

use burn::module::Module;

use crate::NetsError;

/// Writes `module`'s parameters to `path` (temporary file, then rename).
pub fn save<M: Module>(module: M, path: &Path) -> Result<(), NetsError> {
    let bytes = module
        .into_record()
        .into_bytes()
        .map_err(|e| NetsError::weights(path, e))?;
    f3g_io::write_atomic(path, &bytes).map_err(|e| NetsError::weights(path, e.reason))
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
