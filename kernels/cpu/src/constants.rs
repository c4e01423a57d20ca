//! Constants of the host passes, each with its reason, in one place.

/// Negative slope of every LeakyReLU (method §3; RGCA and the authors' code use 0.2).
pub const LEAKY_RELU_SLOPE: f64 = 0.2;

/// Values a rayon task of the layers' host passes (scatter, gather, bias + activation) covers
/// at least. With one task per plane, the decoders' first layers (16 x 16 and 32 x 32 planes)
/// make tasks of a few microseconds, and waking a worker costs about as much, so the
/// hand-offs between threads would take a large share of the small decoders' time.
pub const MIN_TASK_VALUES: usize = 1 << 14;

/// Planes of `plane` values per rayon task, so a task covers at least [`MIN_TASK_VALUES`].
pub fn planes_per_task(plane: usize) -> usize {
    (MIN_TASK_VALUES / plane.max(1)).max(1)
}

/// Values of a transposed convolution's column matrix (`C_out·k_h·k_w` rows by the pixels of
/// some input rows) that one block of its host passes forms and uses while it is still in
/// cache: 2^18 floats, 1 MiB, half the L2 of one core of the 2-core machine. As one matrix
/// over the whole input, the `paper` decoders' two largest layers would make columns of tens
/// of MB, and a product whose operand does not fit the cache runs several times slower than
/// one whose columns do (docs/performance.md).
pub const COLUMN_BLOCK: usize = 1 << 18;
