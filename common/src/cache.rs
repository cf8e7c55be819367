//! A hint to the CPU's cache, for passes that read large arrays at random places.

/// Asks the CPU to bring the cache line holding `value` into its caches (all levels), ahead of
/// a read: a hint that changes no result. A pass over edges that reads per-element data at
/// random places of an array much larger than the caches misses on every read; prefetching
/// the data of an element some steps ahead overlaps those misses with the work between them.
/// `_mm_prefetch` with `_MM_HINT_T0` on x86_64, nothing elsewhere.
#[inline(always)]
pub fn prefetch<T>(value: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: a prefetch never faults and changes nothing the program can read; the
        // pointer comes from a reference, so it is valid and aligned.
        #[allow(unsafe_code)]
        unsafe {
            _mm_prefetch::<_MM_HINT_T0>(std::ptr::from_ref(value).cast::<i8>());
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = value;
}

