//! Parameter masking and aggregation: SLAG's per-Gaussian embedding
//!
//! ```text
//!   a_kj = Σ_{p ∈ M_j} w_kp                       (image stage, one image)
//!   E_k  = Σ_i Σ_j a_kj · E_j  /  Σ_i Σ_j a_kj    (reduction over all images)
//! ```
//!
//! The image stage ([`image_contribution`]) turns one image's per-pixel blend weights
//! ([`PixelWeights`]) and masks into the sparse non-zero `a_kj` ([`Entry`]); nothing dense leaves it.
//! Overlapping masks are handled exactly: pixels are grouped by the *set* of masks covering them
//! (a "signature"), weights are summed per (Gaussian, signature), then expanded to each mask of the
//! signature. The reduction ([`reduce`]) accumulates in f64, chunked over Gaussian ids so that the
//! accumulator stays within a memory budget however large the scene, and declares a Gaussian
//! *unobserved* (no embedding) when `Σ a_kj` is below a threshold or the weighted mean vanishes.
//! [`reduce_mixture`] runs the same reduction but keeps each `E_k` as a sparse mixture of the
//! shared mask embeddings (`slag_common::mixture`), the compressed storage form;
//! [`reduce_to_writer_with_mixture`] gives both forms from one pass (the encoder's tail).
//! When only the mixture is written, [`MixtureFold`] folds each view into a running state as it
//! comes instead, so that the host keeps no view; with the dense file, [`DenseFold`] folds each
//! view into f64 accumulators tiled by Gaussian ids (spilled past a budget), with the same sums.
//!
//! One file per step: [`image`] (the image stage: pixel labels, mask weighting, `a_kj` of one
//! image; [`erode`], the masks eroded for it with `--mask-erode`), [`store`] (the [`ContributionStore`] that holds every image's `a_kj` until the
//! reduction, spilling to disk beyond a budget), [`reduce`] (the f64 reduction to `E_k`, in
//! memory or streamed to the embeddings file) and [`mixture`] (the same reduction kept as a sparse
//! mixture). Beyond the paper's mean: [`levels`] (SAM's granularity levels reduced apart, and
//! combined at query time) and [`robust`] (the weighted mode of a Gaussian's mask embeddings
//! instead of their mean). The rasterizer is driven by the pipeline's back stage
//! ([`crate::pipeline::view_contribution`]), not from here: this module is the paper's math only.

pub mod dense_fold;
pub mod erode;
pub mod fold;
pub mod image;
pub mod image_mask;
pub mod levels;
pub mod mixture;
pub mod reduce;
pub mod robust;
pub mod store;
mod top;

pub use dense_fold::{DenseFold, DenseFoldParams, DenseFoldStats, DenseFolded};
pub use fold::{FoldState, MAX_FOLDED_KEEP, MixtureFold};
pub use image::{
    Entry, ImageContribution, ImageStageParams, MaskOverlap, MaskWeighting, PixelLabels,
    image_contribution, overlap_labels, pixel_labels, stage_labels,
};
pub use image_mask::ImageMask;
pub use mixture::{
    StreamedMixture, reduce_mixture, reduce_mixture_chunks, reduce_to_writer_with_mixture,
};
pub use reduce::{
    OUTPUT_CHUNK_BYTES, ReduceParams, Reduced, Streamed, output_chunk_rows, reduce, reduce_each,
    reduce_to_writer,
};
pub use store::{ContributionStore, MaskColumn, StoredImage};

#[cfg(test)]
mod tests;
