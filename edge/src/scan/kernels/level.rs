//! Which instruction set the scan loops run with ([`SimdLevel`]), detected once per process
//! ([`simd_level`]).

/// Which instruction set the scan loops run with (see [`simd_level`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SimdLevel {
    /// The build target's baseline, auto-vectorised portable loops (SSE2 on x86_64; NEON + FMA
    /// on aarch64); f16 rows converted per [`BLOCK`](super::BLOCK) through a stack buffer.
    Baseline,
    /// x86_64 AVX2 + FMA + F16C intrinsics (8 lanes), selected at run time.
    Avx2Fma,
    /// x86_64 AVX-512F intrinsics (16 lanes; `vcvtph2ps zmm` for f16), selected at run time.
    Avx512,
    /// aarch64 NEON intrinsics (FMLA; FCVTL for f16; SXTL + SCVTF for int8).
    Neon,
    /// aarch64 NEON with the dot-product extension: as [`SimdLevel::Neon`], int8 rows with SDOT
    /// against three-term int8 splits of the queries; selected at run time.
    NeonDotprod,
    /// x86_64 AVX-512 with VNNI: as [`SimdLevel::Avx512`], int8 rows with `vpdpbusd` against
    /// three-term int8 splits of the queries; selected at run time.
    Avx512Vnni,
}

impl SimdLevel {
    /// Every level, best last per architecture.
    pub const ALL: [SimdLevel; 6] = [
        SimdLevel::Baseline,
        SimdLevel::Avx2Fma,
        SimdLevel::Avx512,
        SimdLevel::Avx512Vnni,
        SimdLevel::Neon,
        SimdLevel::NeonDotprod,
    ];

    /// `true` when this build target and CPU can run the level (detected at run time with
    /// `is_x86_feature_detected!` / `is_aarch64_feature_detected!`).
    pub fn available(self) -> bool {
        match self {
            SimdLevel::Baseline => true,
            SimdLevel::Avx2Fma => avx2_fma_available(),
            #[cfg(target_arch = "x86_64")]
            SimdLevel::Avx512 => {
                avx2_fma_available() && std::arch::is_x86_feature_detected!("avx512f")
            }
            #[cfg(target_arch = "x86_64")]
            SimdLevel::Avx512Vnni => {
                SimdLevel::Avx512.available()
                    && std::arch::is_x86_feature_detected!("avx512bw")
                    && std::arch::is_x86_feature_detected!("avx512vnni")
            }
            #[cfg(target_arch = "aarch64")]
            SimdLevel::Neon => true,
            #[cfg(target_arch = "aarch64")]
            SimdLevel::NeonDotprod => std::arch::is_aarch64_feature_detected!("dotprod"),
            #[allow(unreachable_patterns)]
            _ => false,
        }
    }

    /// The levels this CPU can run, baseline first, best last.
    pub fn available_levels() -> Vec<SimdLevel> {
        SimdLevel::ALL
            .into_iter()
            .filter(|l| l.available())
            .collect()
    }

    /// Parses `baseline`, `avx2`, `avx512`, `avx512vnni`, `neon`, `dotprod` (case-insensitive).
    pub fn from_name(s: &str) -> Option<SimdLevel> {
        match s.to_ascii_lowercase().as_str() {
            "baseline" => Some(SimdLevel::Baseline),
            "avx2" | "avx2fma" => Some(SimdLevel::Avx2Fma),
            "avx512" => Some(SimdLevel::Avx512),
            "avx512vnni" | "vnni" => Some(SimdLevel::Avx512Vnni),
            "neon" => Some(SimdLevel::Neon),
            "dotprod" | "neondotprod" => Some(SimdLevel::NeonDotprod),
            _ => None,
        }
    }
}

/// The level used by [`scan`](crate::scan::scan): the best available one (AVX-512F, else AVX2 + FMA +
/// F16C on x86_64; NEON + dotprod, else NEON on aarch64), unless the environment variable
/// `SLAG_SCAN_SIMD` names an available level (`baseline`, `avx2`, `avx512`, `neon`, `dotprod`;
/// for measurements). Detected once per process.
pub fn simd_level() -> SimdLevel {
    static LEVEL: std::sync::OnceLock<SimdLevel> = std::sync::OnceLock::new();
    *LEVEL.get_or_init(|| {
        if let Some(l) = std::env::var("SLAG_SCAN_SIMD")
            .ok()
            .and_then(|v| SimdLevel::from_name(&v))
            .filter(|l| l.available())
        {
            return l;
        }
        SimdLevel::available_levels()
            .last()
            .copied()
            .unwrap_or(SimdLevel::Baseline)
    })
}

/// `true` when this CPU can run [`SimdLevel::Avx2Fma`].
pub fn avx2_fma_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
            && std::arch::is_x86_feature_detected!("f16c")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}
