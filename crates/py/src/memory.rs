//! `vesselflow._core.memory_estimate`: the core's estimate of a run's peak memory
//! (`vesselflow::memory`), for benchmarks and for planning chunked runs; and
//! `usable_memory`, the one rule for what this process may still allocate
//! (`vesselflow_io::budget`), which `load_volume` and `max_memory="auto"` share.

use pyo3::prelude::*;
use vesselflow::params::{Connectivity, Params, Value};

/// Estimated peak bytes beyond the mask of a run on a mask of `shape` with `foreground`
/// voxels, as the `max_memory` guard computes it (0 threads: one per core).
#[pyfunction]
#[pyo3(signature = (shape, foreground, connectivity = 6, threads = 0))]
pub fn memory_estimate(shape: [usize; 3], foreground: usize, connectivity: i64, threads: usize) -> PyResult<u64> {
    let mut p = Params::default();
    p.set("connectivity", &Value::Int(connectivity)).map_err(crate::errors::core)?;
    let connectivity: Connectivity = p.connectivity;
    let threads = if threads == 0 { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { threads };
    let context = || format!("memory_estimate({shape:?}, {foreground}, threads {threads})");
    crate::errors::no_panic(context, || vesselflow::memory::estimate(shape, foreground, connectivity, threads).peak())
}

/// Bytes this process may still allocate: the least of the available memory, the
/// control group's room and the `RLIMIT_AS` room; `None` where none is known.
#[pyfunction]
pub fn usable_memory() -> Option<u64> {
    vesselflow_io::budget::usable_memory()
}
