//! Mixture partitions: mixture shards + codebook from a `MixtureEmbeddings`,
//! sized in bytes, stored, exported, refused by the Qdrant upload.

use slag_common::mixture::{MixtureEmbeddings, SparseMixture};
use slag_common::shards::{
    GroundFrame, MIXTURE_MANIFEST_VERSION, decode_codebook, decode_mixture_shard, shard_checksum,
};
use slag_shards::partition::{
    PartitionParams, ShardCap, UpChoice, mixture_layout, partition_mixture_with,
    resolve_mixture_max_per_shard,
};
use slag_shards::store::{ShardStore, partition_mixture_into_store};

/// `n` Gaussians on a 2D grid, each mixing 1..=5 of `m` random unit rows of width `dim`.
fn mixture(n: usize, m: usize, dim: usize) -> MixtureEmbeddings {
    let mut s = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let mut codebook = Vec::new();
    for _ in 0..m {
        let v: Vec<f32> = (0..dim).map(|_| next() - 0.5).collect();
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        codebook.extend(v.iter().map(|x| x / norm));
    }
    let mut parts = SparseMixture {
        dim,
        model_id: "color-clip-visual".into(),
        codebook,
        gaussian_ids: (0..n as u32).map(|i| 2 * i).collect(),
        means: (0..n)
            .map(|i| [(i % 40) as f32, (i / 40) as f32, next()])
            .collect(),
        offsets: vec![0],
        ..Default::default()
    };
    for i in 0..n {
        for t in 0..1 + i % 5 {
            parts.atoms.push(((i * 7 + t * 13) % m) as u32);
            parts.weights.push(0.1 + next() as f32);
        }
        parts.offsets.push(parts.atoms.len());
    }
    MixtureEmbeddings::from_sparse(parts).expect("mixture")
}

fn params(max_per_shard: usize) -> PartitionParams {
    PartitionParams {
        scene_id: "mix".into(),
        max_per_shard,
        up: UpChoice::Given(GroundFrame::from_axis_name("z").expect("z")),
        dtype: slag_common::shards::Dtype::F16,
        to_map: None,
    }
}

#[test]
fn mixture_partitions_hold_every_row_within_the_byte_cap() {
    let full = mixture(1500, 90, 16);
    let mix = full.truncated(3).expect("cut");
    let cap = 8000u64;
    let layout = mixture_layout(&mix, "mix", mix.keep);
    let max = resolve_mixture_max_per_shard(&layout, ShardCap::Bytes(cap)).expect("cap");
    let mut shards = Vec::new();
    let (m, codebook) = partition_mixture_with(&mix, &mix, &params(max), |t, b| {
        shards.push((t.clone(), b));
        Ok(())
    })
    .expect("partition");
    assert_eq!(m.manifest_version, MIXTURE_MANIFEST_VERSION);
    let info = m.mixture.clone().expect("mixture section");
    assert_eq!((info.slots, info.atoms as usize), (3, mix.codebook_len()));
    assert_eq!(
        info.codebook_checksum,
        format!("{:08x}", shard_checksum(&codebook))
    );
    // The signed manifest names the codebook's SHA-256 as it does each tile's.
    assert_eq!(
        info.codebook_sha256.as_deref(),
        Some(slag_common::shards::signature::sha256_hex(&codebook).as_str())
    );
    let book = decode_codebook(&codebook).expect("codebook");
    assert_eq!(book.rows, mix.codebook);
    assert!(shards.len() > 2, "{} shards", shards.len());
    let mut seen = 0;
    for (t, b) in &shards {
        assert!(b.len() as u64 <= cap && b.len() as u64 == layout.shard_len(t.count));
        let s = decode_mixture_shard(b).expect("shard");
        assert_eq!(format!("{:08x}", s.codebook_crc), info.codebook_checksum);
        for (r, id) in s.ids.iter().enumerate() {
            let i = mix.gaussian_ids.binary_search(id).expect("known id");
            assert_eq!(s.means[r], mix.means[i]);
            assert_eq!(s.atoms[r * 3..(r + 1) * 3], mix.atoms[i * 3..(i + 1) * 3]);
            let w: Vec<f32> = s.weights[r * 3..(r + 1) * 3]
                .iter()
                .map(|x| x.to_f32())
                .collect();
            assert_eq!(w, mix.weights[i * 3..(i + 1) * 3]);
            seen += 1;
        }
    }
    assert_eq!(seen, mix.len());
    // A budget below one Gaussian's shard is a typed error naming the size needed.
    assert!(matches!(
        resolve_mixture_max_per_shard(&layout, ShardCap::Bytes(50)),
        Err(slag_common::Error::Param {
            name: "max_shard_mib",
            ..
        })
    ));
}

#[test]
fn stores_and_exports_carry_the_codebook_and_qdrant_refuses_mixtures() {
    let dir = tempfile::tempdir().expect("tmp");
    let store = ShardStore::open(&dir.path().join("store")).expect("open");
    let mix = mixture(700, 40, 8);
    let m = partition_mixture_into_store(&store, &mix, &mix, &params(200)).expect("partition");
    let info = m.mixture.clone().expect("mixture");
    let cb = store.codebook("mix").expect("read").expect("stored");
    assert_eq!(
        format!("{:08x}", shard_checksum(&cb)),
        info.codebook_checksum
    );
    let shards: u64 = m.tiles.iter().map(|t| t.bytes).sum();
    assert_eq!(
        store.scene_bytes("mix").expect("bytes"),
        Some(shards + info.codebook_bytes)
    );
    let out = dir.path().join("export");
    slag_shards::export::export(&store, "mix", &out, false).expect("export");
    assert_eq!(
        std::fs::read(out.join("codebook")).expect("file"),
        cb.to_vec()
    );
    // A later dense partition of the scene leaves no codebook behind.
    let emb = slag_common::embeddings::Embeddings {
        ids: mix.gaussian_ids.clone(),
        means: mix.means.clone(),
        dim: mix.dim,
        vectors: mix.to_dense(),
        total_weights: vec![1.0; mix.len()],
        ..Default::default()
    };
    let err = slag_shards::qdrant::upload(
        &emb,
        &m,
        &slag_shards::qdrant::QdrantParams {
            url: "http://127.0.0.1:1".into(),
            collection: "mix".into(),
            batch_size: 16,
            quantize_int8: false,
            snapshot_per_tile: false,
            api_key: None,
        },
    )
    .expect_err("a mixture scene is not uploaded");
    assert!(
        matches!(
            err,
            slag_common::Error::Param {
                name: "qdrant_url",
                ..
            }
        ),
        "{err}"
    );
    let dense = slag_shards::store::partition_into_store(&store, &emb, &params(200))
        .expect("dense partition");
    assert!(dense.mixture.is_none());
    assert!(store.codebook("mix").expect("read").is_none());
}

#[test]
fn mixture_shards_carry_the_segments_of_their_gaussians() {
    use slag_common::segments::{Segments, canonical_ids};
    use slag_common::shards::{
        MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION, MIXTURE_SHARD_FORMAT_VERSION, WithSegments,
    };
    let mix = mixture(900, 40, 8).truncated(2).expect("cut");
    // Ids are 0, 2, 4, … (mixture()): segments over the .ply's 1800 Gaussians, 7 ids each.
    let (segments, segment_count) = canonical_ids(&(0..1800u32).map(|i| i / 7).collect::<Vec<_>>());
    let segs = Segments {
        segments,
        segment_count,
        ..Default::default()
    };
    let src = WithSegments::new(&mix, &segs).expect("segments cover the ids");
    let layout = mixture_layout(&src, "mix", mix.keep);
    let mut shards = Vec::new();
    let (m, _) = partition_mixture_with(&src, &mix, &params(250), |t, b| {
        shards.push((t.clone(), b));
        Ok(())
    })
    .expect("partition");
    assert_eq!(
        m.shard_format_version,
        MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION
    );
    assert!(shards.len() > 2);
    let mut seen = 0;
    for (t, b) in &shards {
        assert_eq!(b.len() as u64, layout.shard_len(t.count));
        let s = decode_mixture_shard(b).expect("shard");
        assert_eq!(s.header.version, MIXTURE_SEGMENTS_SHARD_FORMAT_VERSION);
        let got = s.segments.as_ref().expect("segments in the shard");
        for (r, id) in s.ids.iter().enumerate() {
            assert_eq!(got[r], id / 7, "Gaussian {id}");
            seen += 1;
        }
    }
    assert_eq!(seen, mix.len());
    // Without segments: version 2 and no segment section, as before.
    let (m, _) = partition_mixture_with(&mix, &mix, &params(250), |_, b| {
        assert!(decode_mixture_shard(&b).expect("shard").segments.is_none());
        Ok(())
    })
    .expect("partition");
    assert_eq!(m.shard_format_version, MIXTURE_SHARD_FORMAT_VERSION);
}
