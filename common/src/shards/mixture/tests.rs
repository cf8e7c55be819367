#![allow(clippy::unwrap_used)]

use super::*;
use crate::shards::format::{
    SHARD_FORMAT_VERSION, assert_checksum_error, decode_header, decode_shard, fingerprint,
};
use crate::shards::{StoredVectors, shard_checksum};
use proptest::prelude::*;

/// A random mixture shard's content: N rows of S slots over A atoms, optional display columns.
#[derive(Debug, Clone)]
struct Case {
    dim: usize,
    slots: usize,
    ids: Vec<u32>,
    means: Vec<[f32; 3]>,
    atoms: Vec<u32>,
    weights: Vec<f32>,
    display: bool,
    /// Segment ids (`id % 5`) in the shard (format version 4).
    segments: bool,
}

fn case() -> impl Strategy<Value = Case> {
    (
        0usize..40,
        1usize..10,
        1usize..24,
        any::<u64>(),
        any::<bool>(),
        any::<bool>(),
    )
        .prop_map(|(n, slots, dim, seed, display, segments)| {
            let mut s = seed | 1;
            let mut next = move || {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                s
            };
            let mut atoms = Vec::new();
            let mut weights = Vec::new();
            for _ in 0..n * slots {
                if next() % 5 == 0 {
                    atoms.push(UNUSED);
                    weights.push(0.0);
                } else {
                    atoms.push((next() % 50) as u32);
                    weights.push(f16::from_f32((next() % 1000) as f32 / 300.0).to_f32());
                }
            }
            Case {
                dim,
                slots,
                ids: (0..n as u32).map(|i| 2 * i + 1).collect(),
                means: (0..n)
                    .map(|i| [i as f32, -(i as f32) * 0.5, (next() % 100) as f32])
                    .collect(),
                atoms,
                weights,
                display,
                segments,
            }
        })
}

fn encode(c: &Case) -> Vec<u8> {
    let n = c.ids.len();
    let scales = vec![[0.1f32, -0.2, 0.3]; n];
    let opac = vec![0.5f32; n];
    let rot = vec![[1.0f32, 0.0, 0.0, 0.0]; n];
    let segments: Vec<u32> = c.ids.iter().map(|i| i % 5).collect();
    encode_mixture_shard(&MixtureShardInput {
        scene_id: "scene-a",
        model: "color-clip",
        tile_id: 7,
        dim: c.dim,
        slots: c.slots,
        codebook_crc: 0xfeed_beef,
        ids: &c.ids,
        means: &c.means,
        atoms: &c.atoms,
        weights: &c.weights,
        scales: c.display.then_some(scales.as_slice()),
        opacities: c.display.then_some(opac.as_slice()),
        rotations: c.display.then_some(rot.as_slice()),
        sh_dc: None,
        segments: c.segments.then_some(segments.as_slice()),
    })
    .unwrap()
}

/// The bytes on disk do not drift: the [`fingerprint`] of mixture shards of fixed content
/// ([`encode`]: plain, then with the display and segment sections) as this format writes them.
#[test]
fn encoded_bytes_are_stable() {
    let plain = Case {
        dim: 8,
        slots: 2,
        ids: vec![3, 1, 4],
        means: vec![[0.5, -1.0, 2.0], [1e3, 0.0, -7.25], [0.0; 3]],
        atoms: vec![0, 2, 1, UNUSED, 5, 4],
        weights: vec![0.75, 0.25, 1.0, 0.0, -0.5, 0.125],
        display: false,
        segments: false,
    };
    let full = Case {
        display: true,
        segments: true,
        ..plain.clone()
    };
    let got: Vec<(usize, u32)> = [plain, full]
        .iter()
        .map(|c| {
            let bytes = encode(c);
            fingerprint(&bytes)
        })
        .collect();
    assert_eq!(got, GOLDEN_MIXTURE, "{got:x?}");
}

/// [`fingerprint`]s: plain (version 2), then with the optional sections (version 4).
const GOLDEN_MIXTURE: [(usize, u32); 2] = [(188, 0x2722_3d72), (296, 0xda00_5978)];

fn layout(c: &Case) -> MixtureLayout {
    MixtureLayout {
        base: ShardLayout {
            dtype: Dtype::F16,
            dim: c.dim,
            scales: c.display,
            opacities: c.display,
            rotations: c.display,
            sh_dc: false,
            segments: c.segments,
            scene_id_len: "scene-a".len(),
            model_len: "color-clip".len(),
        },
        slots: c.slots,
    }
}

proptest! {
    #[test]
    fn mixture_shards_round_trip(c in case()) {
        let bytes = encode(&c);
        let s = decode_mixture_shard(&bytes).unwrap();
        // Segments make it version 4; without them it stays version 2.
        prop_assert_eq!(
            s.header.version,
            if c.segments { MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION } else { MIXTURE_SHARD_FORMAT_VERSION }
        );
        let want: Option<Vec<u32>> = c.segments.then(|| c.ids.iter().map(|i| i % 5).collect());
        prop_assert_eq!(&s.segments, &want);
        prop_assert_eq!(s.header.dtype, Dtype::F16);
        prop_assert_eq!(s.header.dim as usize, c.dim);
        prop_assert_eq!(s.header.tile_id, 7);
        prop_assert_eq!(s.slots as usize, c.slots);
        prop_assert_eq!(s.codebook_crc, 0xfeed_beef);
        prop_assert_eq!(&s.ids, &c.ids);
        prop_assert_eq!(&s.means, &c.means);
        prop_assert_eq!(&s.atoms, &c.atoms);
        let w: Vec<f32> = s.weights.iter().map(|x| x.to_f32()).collect();
        prop_assert_eq!(&w, &c.weights);
        prop_assert_eq!(s.scales.is_some(), c.display);
        prop_assert_eq!(s.rotations.is_some(), c.display);
        prop_assert!(s.sh_dc.is_none());
        // The header alone reads too; dense decoders refuse by type, not as corruption.
        prop_assert_eq!(decode_header(&bytes).unwrap(), s.header.clone());
        prop_assert_eq!(decode_shard_stored(&bytes), Err(ShardError::MixtureRows { tile_id: 7 }));
        prop_assert_eq!(decode_shard(&bytes), Err(ShardError::MixtureRows { tile_id: 7 }));
    }

    #[test]
    fn layout_predicts_the_length_and_the_cap(c in case(), budget in 0u64..3000) {
        let l = layout(&c);
        prop_assert_eq!(l.shard_len(c.ids.len() as u64), encode(&c).len() as u64);
        let n = l.max_rows_within(budget);
        if n > 0 {
            prop_assert!(l.shard_len(n) <= budget);
        }
        prop_assert!(l.shard_len(n + 1) > budget);
    }

    #[test]
    fn truncated_mixture_shards_are_typed_errors(c in case(), cut in any::<prop::sample::Index>()) {
        let bytes = encode(&c);
        let at = cut.index(bytes.len());
        let r = decode_mixture_shard(&bytes[..at]);
        prop_assert!(matches!(r, Err(ShardError::Truncated { .. }) | Err(ShardError::BadMagic)), "{:?}", r);
    }

    #[test]
    fn corrupted_mixture_shards_never_panic_and_are_detected(
        c in case(), at in any::<prop::sample::Index>(), flip in 1u8..=255,
    ) {
        let mut bytes = encode(&c);
        let i = at.index(bytes.len());
        bytes[i] ^= flip;
        prop_assert!(decode_mixture_shard(&bytes).is_err());
        prop_assert!(decode_codebook(&bytes).is_err());
    }

    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        let _ = decode_mixture_shard(&bytes);
        let _ = decode_codebook(&bytes);
    }
}

#[test]
fn dense_shards_and_other_versions_get_specific_errors() {
    let dense = encode_shard(&ShardInput {
        scene_id: "s",
        model: "m",
        tile_id: 3,
        dim: 4,
        dtype: Dtype::F16,
        ids: &[1, 2],
        means: &[[0.0; 3]; 2],
        vectors: &[0.5; 8],
        ..Default::default()
    })
    .unwrap();
    assert_eq!(decode_header(&dense).unwrap().version, SHARD_FORMAT_VERSION);
    assert!(matches!(
        decode_mixture_shard(&dense),
        Err(ShardError::Malformed(m)) if m.contains("dense shard")
    ));
    // A shard is not a codebook (its tile id is a tile's).
    assert!(matches!(
        decode_codebook(&dense),
        Err(ShardError::Malformed(m)) if m.contains("not a slag codebook")
    ));
    // A future version is refused by number.
    let c = Case {
        dim: 3,
        slots: 2,
        ids: vec![5],
        means: vec![[1.0, 2.0, 3.0]],
        atoms: vec![0, UNUSED],
        weights: vec![1.0, 0.0],
        display: false,
        segments: false,
    };
    let mut v5 = encode(&c);
    v5[8] = 5;
    assert_eq!(
        decode_mixture_shard(&v5),
        Err(ShardError::UnsupportedVersion(5))
    );
    // A version-2 shard claiming version 4 lacks the required segments flag: refused (the
    // header CRC is recomputed so that the version check is what refuses it).
    let mut v4 = encode(&c);
    v4[8] = 4;
    let hl = u32::from_le_bytes([v4[20], v4[21], v4[22], v4[23]]) as usize;
    let crc = crc32fast::hash(&v4[..hl - 4]);
    v4[hl - 4..hl].copy_from_slice(&crc.to_le_bytes());
    assert!(matches!(
        decode_mixture_shard(&v4),
        Err(ShardError::Malformed(m)) if m.contains("format version 4 without its segments")
    ));
    // With segments: version 4, which the dense decoders refuse as mixture rows, not corruption.
    let seg = Case {
        segments: true,
        ..c
    };
    let bytes = encode(&seg);
    assert_eq!(decode_header(&bytes).unwrap().version, 4);
    assert_eq!(
        decode_mixture_shard(&bytes).unwrap().segments,
        Some(vec![0])
    );
    assert_eq!(
        decode_shard(&bytes),
        Err(ShardError::MixtureRows { tile_id: 7 })
    );
}

#[test]
fn bad_mixture_input_is_refused_before_writing() {
    let base = MixtureShardInput {
        scene_id: "s",
        model: "m",
        tile_id: 0,
        dim: 4,
        slots: 2,
        codebook_crc: 0,
        ids: &[1],
        means: &[[0.0; 3]],
        atoms: &[0, UNUSED],
        weights: &[1.0, 0.0],
        ..Default::default()
    };
    assert!(encode_mixture_shard(&base).is_ok());
    let mut seg = base;
    seg.segments = Some(&[1, 2]);
    assert!(matches!(
        encode_mixture_shard(&seg),
        Err(Error::Internal(_))
    ));
    let mut w = base;
    w.weights = &[1e6, 0.0];
    assert!(matches!(encode_mixture_shard(&w), Err(Error::Invalid(_))));
    let mut e = base;
    e.weights = &[1.0, 0.5];
    assert!(matches!(encode_mixture_shard(&e), Err(Error::Invalid(_))));
    let mut z = base;
    z.slots = 0;
    assert!(matches!(
        encode_mixture_shard(&z),
        Err(Error::Param {
            name: "mixture_slots",
            ..
        })
    ));
    let mut short = base;
    short.atoms = &[0];
    assert!(matches!(
        encode_mixture_shard(&short),
        Err(Error::Internal(_))
    ));
}

#[test]
fn codebooks_round_trip_and_corruption_is_typed() {
    let rows: Vec<f32> = (0..5 * 6)
        .map(|i| f16::from_f32((i as f32 * 0.37).sin()).to_f32())
        .collect();
    let bytes = encode_codebook("scene-a", "color-clip", 6, &rows).unwrap();
    let cb = decode_codebook(&bytes).unwrap();
    assert_eq!(cb.rows, rows);
    assert_eq!((cb.len(), cb.dim), (5, 6));
    assert_eq!(
        (cb.scene_id.as_str(), cb.model.as_str()),
        ("scene-a", "color-clip")
    );
    assert_eq!(decode_header(&bytes).unwrap().tile_id, CODEBOOK_TILE);
    // Truncated: typed, at every cut.
    for cut in 0..bytes.len() {
        assert!(decode_codebook(&bytes[..cut]).is_err(), "cut {cut}");
    }
    // One flipped payload byte: a payload checksum error.
    let mut bad = bytes.clone();
    let last = bad.len() - 1;
    bad[last] ^= 0x40;
    assert_checksum_error(decode_codebook(&bad), "payload");
    assert_ne!(shard_checksum(&bad), shard_checksum(&bytes));
    // Rows of another width are not a codebook of that width.
    assert!(encode_codebook("s", "m", 4, &rows).is_err());
    // A codebook has f16 vectors.
    assert!(matches!(
        decode_shard_stored(&bytes).unwrap().vectors,
        StoredVectors::F16(_)
    ));
}

#[test]
fn files_written_from_the_documented_layout_decode() {
    // The fuzz seeds were written by a 30-line Python script from the module doc's layout
    // (struct + zlib.crc32), independently of this encoder.
    let cb = include_bytes!("../../../../fuzz/corpus/mixture_decode/codebook");
    let ms = include_bytes!("../../../../fuzz/corpus/mixture_decode/mixture_shard");
    let book = decode_codebook(cb).unwrap();
    assert_eq!(
        book.rows[8..10],
        [0.6f32, 0.8].map(|v| f16::from_f32(v).to_f32())
    );
    let s = decode_mixture_shard(ms).unwrap();
    assert_eq!(s.codebook_crc, shard_checksum(cb));
    assert_eq!(s.ids, vec![3, 5, 9]);
    assert_eq!(s.atoms, vec![0, 2, 1, UNUSED, 2, UNUSED]);
    assert_eq!(s.weights[0], f16::from_f32(0.7));
    assert_eq!(s.means[2], [-2.0, 0.0, 4.0]);
}
