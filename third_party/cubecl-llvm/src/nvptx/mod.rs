//! NVPTX target: only the PTX version `cubecl-cuda` reads off the driver.

pub mod ptx_version;
