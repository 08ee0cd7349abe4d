//! Counting the distinct kernels CubeCL launches (its `LaunchedKernels`): in a fresh process,
//! each is compiled once at its first launch, so the count of a cold step is what that step
//! compiles, autotune's candidates included. Only GPU builds run CubeCL kernels.

#[cfg(any(feature = "gpu", feature = "cuda"))]
pub use burn::cubecl::launched::LaunchedKernels as Counting;

/// Nothing to count in a CPU-only build.
#[cfg(not(any(feature = "gpu", feature = "cuda")))]
pub type Counting = std::convert::Infallible;

/// Starts counting when `on_gpu` (a CPU device launches no CubeCL kernels).
#[cfg(any(feature = "gpu", feature = "cuda"))]
pub fn start(on_gpu: bool) -> Option<Counting> {
    on_gpu.then(Counting::new)
}

/// A CPU-only build has nothing to count.
#[cfg(not(any(feature = "gpu", feature = "cuda")))]
pub fn start(_on_gpu: bool) -> Option<Counting> {
    None
}

/// The distinct kernels launched since [`start`].
#[cfg(any(feature = "gpu", feature = "cuda"))]
pub fn finish(counting: Counting) -> usize {
    counting.finish().len()
}

/// Never called: a CPU-only build starts no count.
#[cfg(not(any(feature = "gpu", feature = "cuda")))]
pub fn finish(counting: Counting) -> usize {
    match counting {}
}
