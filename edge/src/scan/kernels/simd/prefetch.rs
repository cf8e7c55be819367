//! Cache-line prefetch hints of the explicit kernels (a hint never faults, whatever the address).

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};

/// `prefetcht0` (SSE, part of the x86_64 baseline).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) fn prefetch_t0(p: *const u8) {
    // SAFETY: SSE is in the x86_64 baseline; a prefetch is a hint that never faults and
    // reads nothing visible to the program, whatever the address.
    unsafe { _mm_prefetch::<_MM_HINT_T0>(p.cast()) }
}

/// `prfm pldl1keep` (a hint: never faults).
#[cfg(target_arch = "aarch64")]
#[inline(always)]
pub(super) fn prefetch_l1(p: *const u8) {
    // SAFETY: PRFM is a base AArch64 instruction; a prefetch never faults and has no effect
    // visible to the program, whatever the address.
    unsafe {
        std::arch::asm!(
            "prfm pldl1keep, [{p}]",
            p = in(reg) p,
            options(nostack, preserves_flags, readonly)
        );
    }
}
