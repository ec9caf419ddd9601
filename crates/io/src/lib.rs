//! # vesselflow-io
//!
//! The file layer shared by the `vesselflow` command-line program and the Python
//! bindings: the input rule ([`MaskRule`], [`binarise`]: which images are masks and how
//! others become one), vessel masks in ([`read_volume`]: `.npy`, `.npz`, `.nii`, `.nii.gz`, `.tif`)
//! and centreline graphs out ([`write_graph`], the one registry of graph formats,
//! [`GraphFormat`]: `.graphml`, `.json`, `.npz` in the `vesselflow-graph` format,
//! version 1, and `.swc`, `.vtp`, `.csv`, `.precomputed`). Every failure is an [`IoError`]
//! whose message names the file and the problem; nothing here panics on bad input,
//! and no partial output file is ever left behind. Readers take a memory budget
//! ([`read_volume_limited`], [`ReadLimits`]; by default what [`budget::usable_memory`]
//! says this process may still use, at most 64 GiB) and refuse a file that
//! declares more ([`IoError::TooLarge`]) before allocating or inflating it.
//!
//! ```no_run
//! use std::path::Path;
//! use vesselflow::{Params, Skeletonizer};
//!
//! let volume = vesselflow_io::read_volume(Path::new("mask.nii.gz"))?;
//! let params = Params::default();
//! let skel = Skeletonizer::new(params.clone())?
//!     .run(volume.mask.view(), volume.spacing, &mut |_| true)?;
//! vesselflow_io::write_graph(Path::new("graph.json"), &skel, &params)?;
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod binarise;
pub mod budget;
mod coords;
mod error;
mod graph;
mod volume;

pub use binarise::{binarise, Binariser, MaskRule, Sample, MASK_ADVICE};
pub use coords::{check_affine, to_frame, Coordinates, Frame};
pub use error::IoError;
pub use graph::{
    check_graph_output, check_writable, frame_info, params_json, replace_all, run_info_json, temp_dir_beside,
    write_atomically, write_graph, write_graph_arrays, write_skeleton, GraphArrays, GraphFormat, FORMAT_NAME,
    FORMAT_VERSION,
};
/// The JSON library of [`GraphArrays`]' metadata, so callers need no dependency of their own.
pub use serde_json;
pub use volume::{
    read_volume, read_volume_key, read_volume_limited, read_volume_with_spacing, spacing_affine, ReadLimits, VolumeFile,
};
